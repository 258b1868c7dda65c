"""Quadratic generalised moving least squares (Q-GMLS) shape functions (PIE-NeRF §4.2, Eq. 5–9).

Each kernel ``i`` sits at a rest position ``x_i`` with a support radius ``ρ_i`` and carries, per
displacement component, its value ``u_i``, first derivatives ``u_i,j`` and second derivatives
``u_i,jk``. At a point ``x`` the local quadratic polynomial is fitted to those data by weighted least
squares (Eq. 6–8) and evaluated at ``x``; the coefficients of the data in that fit are the shape
functions ``N_i``, ``N_i^j``, ``N_i^jk`` (Eq. 7).

DOF layout, shared by the whole pipeline:

* ``q`` has shape ``[n, T, 3]`` (kernel, term, xyz) with ``T = 10`` terms per kernel ordered
  :data:`QUADRATIC_TERMS` = value, ∂x, ∂y, ∂z, ∂xx, ∂xy, ∂xz, ∂yy, ∂yz, ∂zz; its flat index is
  ``(i * T + t) * 3 + a``. The *shape index* ``s = i * T + t`` runs over ``[0, n T)``, and
  ``u(x) = Σ_s N_s(x) q_s`` (Eq. 9), ``J(x) = N(x) ⊗ I3``.
* The stored DOFs are the derivatives themselves: ``q[i, 1 + j, a] = ∂u_a/∂x_j`` and for the pair
  ``j ≤ k`` ``q[i, t, a] = ∂²u_a/∂x_j∂x_k`` (the mixed ∂xy DOF is the mixed second derivative, not
  twice it). Accordingly ``p_,jk = ∂²p/∂x_j∂x_k`` and each unordered pair appears once in Eq. 8, so a
  quadratic field whose DOFs are set from its analytic derivatives has zero least-squares residual
  and is reproduced exactly (the patch test).
* Units: value DOFs are lengths, first-derivative DOFs are dimensionless, second-derivative DOFs are
  inverse lengths. Eq. 8 adds squared residuals of all three kinds with unit weights, so the fit (and
  hence ``N``) depends on the unit of length: the derivative terms weigh ``1/ℓ²`` and ``1/ℓ⁴``
  relative to the value term when lengths are measured in units of ``ℓ``. We follow the paper and
  measure lengths in scene units.

Conditioning: the polynomial basis is centred at the evaluation point and scaled by a local length
``ℓ`` (the mean support radius of the kernels covering ``x``), i.e. ``p((x_i − x) / ℓ)`` with
derivatives taken in world units. For a complete polynomial basis any invertible linear change of
basis (a shift or a scaling is one) spans the same polynomials and yields the same least-squares fit,
so the shape functions are exactly those of Eq. 7; only the condition number of ``G`` changes.
In the shifted basis ``p(x)`` of Eq. 7 becomes ``p(0) = e_0``.

Derivatives: ``∇N`` and ``∇²N`` are exact and analytic. Because ``N`` does not depend on where the
basis is centred, the centre ``c`` is held fixed while differentiating (and set to ``x`` afterwards):
the basis rows ``b_i`` at the kernels are then constants, ``G(x) = Σ_i w_i(x) B_i`` with
``B_i = Σ_t b_it b_itᵀ``, and differentiating ``G γ = p(x − c)`` gives ``γ_,j = G⁻¹(p_,j − G_,j γ)``
and ``γ_,jk = G⁻¹(p_,jk − G_,jk γ − G_,j γ_,k − G_,k γ_,j)``, from which ``N_s = (γᵀ b_s) w_s``
follows by the product rule. Tests check them against finite differences.

Everything here is precomputation done once per object, in float64 torch on the tensors' device.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = [
    "AFFINE_TERMS",
    "EXACT_CDIST",
    "LINEAR_TERMS",
    "ORDERS",
    "QUADRATIC_TERMS",
    "QGMLSBasis",
    "ShapeValues",
    "as_points",
    "mls_weight",
    "moment_matrix",
    "polynomial_terms",
    "shape_functions",
    "support_radii",
    "voronoi_partition",
]

QUADRATIC_TERMS = ("value", "dx", "dy", "dz", "dxx", "dxy", "dxz", "dyy", "dyz", "dzz")
"""The ``T = 10`` DOF terms of a Q-GMLS kernel, in storage order."""

AFFINE_TERMS = ("value",)
"""The single DOF term of a classical affine MLS kernel."""

LINEAR_TERMS = ("value", "dx", "dy", "dz")
"""The ``T = 4`` DOF terms of a linear GMLS kernel (affine basis with first-derivative terms)."""

ORDERS = ("quadratic", "linear", "affine")

_TERM_ORDER = {"quadratic": (0, 1, 1, 1, 2, 2, 2, 2, 2, 2), "linear": (0, 1, 1, 1), "affine": (0,)}
_TERM_NAMES = {"quadratic": QUADRATIC_TERMS, "linear": LINEAR_TERMS, "affine": AFFINE_TERMS}
_SECOND_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_SECOND_ROWS = ((4, 5, 6), (5, 7, 8), (6, 8, 9))  # quadratic term row of ∂_jk, by (j, k)
_RCOND_MIN = 1e-10
_CHUNK = 1024
EXACT_CDIST = "donot_use_mm_for_euclid_dist"
"""``compute_mode`` of ``torch.cdist`` that measures by differences: exact zeros, no cancellation."""


def mls_weight(d: torch.Tensor) -> torch.Tensor:
    """MLS weighting function ``w(d) = (1 − ‖d‖²)³`` for ``‖d‖ < 1``, else 0 (PIE-NeRF §4.2, after Eq. 5).

    ``w`` is C² across the support boundary (it and its first two derivatives vanish at ``‖d‖ = 1``),
    so the shape functions and their first and second derivatives are continuous.

    Args:
        d: ``[..., 3]`` offsets ``(x − x_i) / ρ_i`` scaled by the kernel's support radius (dimensionless).

    Returns:
        ``[...]`` weights in ``[0, 1]``.
    """
    return (1.0 - (d * d).sum(-1)).clamp_min(0.0) ** 3


def _mls_weight_jet(offset: torch.Tensor, radius: torch.Tensor, derivatives: int) -> tuple[torch.Tensor, ...]:
    """``w``, ``∂w/∂x`` and ``∂²w/∂x∂x`` of :func:`mls_weight` at ``d = (x − x_i) / ρ_i`` (offset = ``x − x_i``).

    With ``s = 1 − ‖d‖²`` (clamped at 0): ``w = s³``, ``w_,j = −6 s² d_j / ρ``,
    ``w_,jk = (24 s d_j d_k − 6 s² δ_jk) / ρ²``.
    """
    radius = radius.unsqueeze(-1)
    d = offset / radius
    s = (1.0 - (d * d).sum(-1)).clamp_min(0.0)
    jet = [s**3]
    if derivatives >= 1:
        jet.append(-6.0 * (s * s).unsqueeze(-1) * d / radius)
    if derivatives >= 2:
        eye = torch.eye(3, dtype=d.dtype, device=d.device)
        outer = d.unsqueeze(-1) * d.unsqueeze(-2)
        s = s[..., None, None]
        jet.append((24.0 * s * outer - 6.0 * s * s * eye) / radius.unsqueeze(-1) ** 2)
    return tuple(jet)


def polynomial_terms(y: torch.Tensor, order: str = "quadratic") -> torch.Tensor:
    """The polynomial basis ``p(y)`` and its derivatives ``p_,j``, ``p_,jk`` stacked by DOF term (Eq. 6–8).

    Quadratic basis (10 monomials): ``p = [1, x, y, z, x², xy, xz, y², yz, z²]``; the rows are
    ``[p, p_,x, p_,y, p_,z, p_,xx, p_,xy, p_,xz, p_,yy, p_,yz, p_,zz]`` with ``p_,jk = ∂²p/∂x_j∂x_k``
    (see the module docstring for why the mixed rows are not doubled). Linear basis: ``p = [1, x, y, z]``
    with rows ``[p, p_,x, p_,y, p_,z]`` (generalised MLS of first order). Affine basis: the single row
    ``p = [1, x, y, z]`` (classical MLS, no derivative terms).

    Args:
        y: ``[..., 3]`` coordinates.
        order: ``"quadratic"``, ``"linear"`` or ``"affine"``.

    Returns:
        ``[..., T, P]``: ``T = 10, P = 10`` (quadratic), ``T = 4, P = 4`` (linear) or ``T = 1, P = 4`` (affine).
    """
    x0, x1, x2 = y.unbind(-1)
    one, zero = torch.ones_like(x0), torch.zeros_like(x0)
    if order == "affine":
        return torch.stack([one, x0, x1, x2], -1).unsqueeze(-2)
    if order == "linear":
        rows = [[one, x0, x1, x2], [zero, one, zero, zero], [zero, zero, one, zero], [zero, zero, zero, one]]
        return torch.stack([torch.stack(row, -1) for row in rows], -2)
    if order != "quadratic":
        raise ValueError(f"unknown order {order!r}; valid orders: {', '.join(ORDERS)}")
    two = 2.0 * one
    rows = [
        [one, x0, x1, x2, x0 * x0, x0 * x1, x0 * x2, x1 * x1, x1 * x2, x2 * x2],
        [zero, one, zero, zero, 2.0 * x0, x1, x2, zero, zero, zero],
        [zero, zero, one, zero, zero, x0, zero, 2.0 * x1, x2, zero],
        [zero, zero, zero, one, zero, zero, x0, zero, x1, 2.0 * x2],
        [zero, zero, zero, zero, two, zero, zero, zero, zero, zero],
        [zero, zero, zero, zero, zero, one, zero, zero, zero, zero],
        [zero, zero, zero, zero, zero, zero, one, zero, zero, zero],
        [zero, zero, zero, zero, zero, zero, zero, two, zero, zero],
        [zero, zero, zero, zero, zero, zero, zero, zero, one, zero],
        [zero, zero, zero, zero, zero, zero, zero, zero, zero, two],
    ]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def moment_matrix(weight: torch.Tensor, terms: torch.Tensor) -> torch.Tensor:
    """Moment matrix ``G(x) = Σ_i w_i [p pᵀ + Σ_j p_,j p_,jᵀ + Σ_jk p_,jk p_,jkᵀ](x_i)`` (Eq. 8).

    For the affine basis (one term) this is the classical MLS ``G = Σ_i w_i p(x_i) p(x_i)ᵀ`` (§4.2).

    Args:
        weight: ``[..., A]`` weights ``w(x − x_i)`` of the ``A`` kernels (zero for padding).
        terms: ``[..., A, T, P]`` basis rows at the kernel centres, from :func:`polynomial_terms`.

    Returns:
        ``[..., P, P]`` symmetric positive semi-definite matrix.
    """
    return torch.einsum("...a,...atp,...atq->...pq", weight, terms, terms)


def shape_functions(
    weight: tuple[torch.Tensor, ...], terms: torch.Tensor, basis_at_x: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, ...]:
    """Q-GMLS shape functions ``N_i = pᵀ(x) G⁻¹(x) p(x_i) w_i``, ``N_i^j``, ``N_i^jk`` and their derivatives (Eq. 7).

    ``N_i^j`` and ``N_i^jk`` replace ``p(x_i)`` by ``p_,j(x_i)`` and ``p_,jk(x_i)``: term ``t`` of
    ``terms`` gives the shape function of DOF term ``t``. The basis rows ``terms`` are held constant
    (the basis centre is fixed, see the module docstring); ``x`` enters through the weights and
    ``p(x)``, whose derivatives come in as jets. Derivatives follow from differentiating
    ``G γ = p(x)`` with ``G`` from Eq. 8 and ``N = (γᵀ b) w``.

    Args:
        weight: jet of the kernel weights, ``(w [..., A], ∇w [..., A, 3], ∇²w [..., A, 3, 3])``, cut
            after the highest derivative wanted (zero for padding kernels).
        terms: ``[..., A, T, P]`` basis rows at the kernel centres, from :func:`polynomial_terms`.
        basis_at_x: jet of the basis at the evaluation point, ``(p [..., P], ∇p [..., 3, P],
            ∇²p [..., 3, 3, P])``, as long as ``weight``.

    Returns:
        ``(N [..., A, T], ∇N [..., A, T, 3], ∇²N [..., A, T, 3, 3])``, as long as ``weight``.
    """
    gram = moment_matrix(weight[0], terms)
    factor = torch.linalg.cholesky(gram)
    moments = torch.einsum("...atp,...atq->...apq", terms, terms)  # B_i, so that G_,j = Σ_i w_i,j B_i

    def solve(rhs: torch.Tensor) -> torch.Tensor:  # G⁻¹ applied to the rows of rhs [..., K, P]
        return torch.cholesky_solve(rhs.mT, factor).mT

    w = weight[0].unsqueeze(-1)
    gamma = solve(basis_at_x[0].unsqueeze(-2)).squeeze(-2)
    fit = torch.einsum("...p,...atp->...at", gamma, terms)
    jet = [fit * w]
    if len(weight) > 1:
        w_grad = weight[1].unsqueeze(-2)
        gram_grad = torch.einsum("...aj,...apq->...jpq", weight[1], moments)
        gamma_grad = solve(basis_at_x[1] - torch.einsum("...jpq,...q->...jp", gram_grad, gamma))
        fit_grad = torch.einsum("...jp,...atp->...atj", gamma_grad, terms)
        jet.append(fit_grad * w.unsqueeze(-1) + fit.unsqueeze(-1) * w_grad)
    if len(weight) > 2:
        gram_hess = torch.einsum("...ajk,...apq->...jkpq", weight[2], moments)
        cross = torch.einsum("...jpq,...kq->...jkp", gram_grad, gamma_grad)
        rhs = basis_at_x[2] - torch.einsum("...jkpq,...q->...jkp", gram_hess, gamma) - cross - cross.transpose(-2, -3)
        gamma_hess = solve(rhs.flatten(-3, -2)).unflatten(-2, (3, 3))
        fit_hess = torch.einsum("...jkp,...atp->...atjk", gamma_hess, terms)
        mixed = fit_grad.unsqueeze(-1) * w_grad.unsqueeze(-2)
        jet.append(
            fit_hess * w[..., None, None]
            + mixed
            + mixed.transpose(-1, -2)
            + fit[..., None, None] * weight[2].unsqueeze(-3)
        )
    return tuple(jet)


def voronoi_partition(points: torch.Tensor, centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Voronoi partition of points by their nearest centre (§4.2).

    Args:
        points: ``[P, 3]`` positions.
        centres: ``[n, 3]`` cell centres.

    Returns:
        ``(cell, distance)``: ``[P]`` int64 index of each point's nearest centre and ``[P]`` the
        distance to it (same units as the positions).
    """
    cells, distances = [], []
    for chunk in points.split(_CHUNK):
        distance, cell = torch.cdist(chunk, centres, compute_mode=EXACT_CDIST).min(dim=1)
        cells.append(cell)
        distances.append(distance)
    return torch.cat(cells), torch.cat(distances)


def support_radii(centres: torch.Tensor, points: torch.Tensor, neighbours: int = 4, scale: float = 1.5) -> torch.Tensor:
    """Support radius ``ρ_i`` of each kernel, chosen so that every point is covered.

    Rule: ``ρ_i = scale · max(d_k(i), r_i)`` where ``d_k(i)`` is the distance from centre ``i`` to its
    ``k``-th nearest other centre (``k = neighbours``, clamped to ``n − 1``) and ``r_i`` is the radius
    of its Voronoi cell over ``points`` (the largest distance from ``x_i`` to a point whose nearest
    centre it is). The cell term guarantees that each point lies strictly inside the support of its
    own kernel (``‖d‖ ≤ 1/scale``, so ``w ≥ (1 − 1/scale²)³``); the neighbour term makes supports
    overlap so that a point is covered by a few kernels and the shape functions blend smoothly.
    With ``k = 4, scale = 1.5`` a point on a regular lattice of kernels sees about 10–20 of them.

    Args:
        centres: ``[n, 3]`` kernel centres.
        points: ``[P, 3]`` points to cover (the particles).
        neighbours: ``k`` ≥ 1.
        scale: factor > 1 (dimensionless).

    Returns:
        ``[n]`` float64 radii, in the units of the positions.
    """
    centres, points = as_points(centres, "centres"), as_points(points, "points")
    if neighbours < 1:
        raise ValueError(f"neighbours must be >= 1, got {neighbours}")
    if not scale > 1.0:
        raise ValueError(f"scale must be > 1 so that each point is strictly inside a support, got {scale}")
    n = centres.shape[0]
    radius = torch.zeros(n, dtype=torch.float64, device=centres.device)
    if points.shape[0] > 0:
        cell, distance = voronoi_partition(points, centres)
        radius = radius.scatter_reduce(0, cell, distance, reduce="amax")
    if n > 1:
        k = min(neighbours, n - 1)
        between = torch.cdist(centres, centres, compute_mode=EXACT_CDIST)
        neighbour_distance = between.topk(k + 1, dim=1, largest=False).values[:, k]
        radius = torch.maximum(radius, neighbour_distance)
    if bool((radius <= 0).any()):
        raise ValueError(
            "a kernel has zero support radius (a single kernel with no points away from its centre); "
            "pass support radii explicitly or more points"
        )
    return scale * radius


@dataclass(frozen=True)
class ShapeValues:
    """Shape functions active at ``M`` points, stored sparsely by shape index ``s = i * T + t``.

    Attributes:
        index: ``[M, S]`` int64 shape indices active at each point, padded with ``-1``.
        value: ``[M, S]`` ``N_s(x)`` (zero where padded).
        grad: ``[M, S, 3]`` ``∂N_s/∂x`` (1/length), or ``None`` when not asked for.
        hess: ``[M, S, 3, 3]`` ``∂²N_s/∂x∂x`` (1/length²), or ``None`` when not asked for.
    """

    index: torch.Tensor
    value: torch.Tensor
    grad: torch.Tensor | None = None
    hess: torch.Tensor | None = None

    def dense_value(self, shape_count: int) -> torch.Tensor:
        """``[M, shape_count]`` dense matrix of ``N_s(x_m)`` (the scalar factor of ``J``, Eq. 9)."""
        dense = torch.zeros(self.index.shape[0], shape_count, dtype=self.value.dtype, device=self.value.device)
        return dense.scatter_add_(1, self.index.clamp_min(0), self.value)


class QGMLSBasis:
    """Q-GMLS (or classical affine MLS) shape functions over a set of kernels (Eq. 5–9).

    Args:
        centres: ``[n, 3]`` kernel centres ``x_i`` at rest (length).
        support_radius: ``[n]`` support radius ``ρ_i`` of each kernel (length), e.g. from
            :func:`support_radii`.
        order: ``"quadratic"`` (Q-GMLS, 10 terms and 30 DOF per kernel), ``"linear"`` (generalised MLS
            of first order: affine basis with value and first-derivative terms, 4 terms and 12 DOF per
            kernel; invertible for colinear centres but, like any linear interpolant, prone to locking
            in bending) or ``"affine"`` (classical MLS with ``p = [1, x, y, z]``, no derivative terms,
            1 term and 3 DOF per kernel; its ``G`` is singular where the centres in a support are coplanar).
        visibility: optional ``(x [M, 3], centres [n, 3]) -> [M, n]`` bool mask of the kernels that may
            influence each point, e.g. :meth:`pienerf.sim.cut.Cut.visibility`; masked kernels are treated
            as outside their support, so a cut separates the pieces on its two sides (§5, Fig. 7).
    """

    def __init__(
        self, centres: torch.Tensor, support_radius: torch.Tensor, order: str = "quadratic", visibility=None
    ):
        if order not in ORDERS:
            raise ValueError(f"unknown order {order!r}; valid orders: {', '.join(ORDERS)}")
        centres = as_points(centres, "centres")
        if centres.shape[0] == 0:
            raise ValueError("QGMLSBasis needs at least one kernel centre")
        support_radius = torch.as_tensor(support_radius, dtype=torch.float64, device=centres.device)
        if support_radius.shape != (centres.shape[0],):
            raise ValueError(
                f"support_radius must be [n] = [{centres.shape[0]}] like centres, got {tuple(support_radius.shape)}"
            )
        if not bool(torch.isfinite(support_radius).all() & (support_radius > 0).all()):
            raise ValueError("support radii must be finite and > 0; compute them with support_radii(centres, points)")
        self.centres = centres
        self.support_radius = support_radius
        self.order = order
        self.term_names = _TERM_NAMES[order]
        self.visibility = visibility
        self._term_derivative_order = torch.tensor(_TERM_ORDER[order], dtype=torch.float64, device=centres.device)
        # Jet of the basis p(x − c) at x = c (value, ∂_j, ∂_jk rows), for the basis of this order.
        origin = torch.zeros(3, dtype=torch.float64, device=centres.device)
        self._basis_rows = polynomial_terms(origin, "quadratic")[:, : 10 if order == "quadratic" else 4]
        self._basis_row_derivative_order = self._term_derivative_order.new_tensor(_TERM_ORDER["quadratic"])
        self._second_rows = torch.tensor(_SECOND_ROWS, device=centres.device)

    @property
    def kernel_count(self) -> int:
        """Number of kernels ``n``."""
        return self.centres.shape[0]

    @property
    def terms(self) -> int:
        """DOF terms per kernel ``T`` (10 quadratic, 1 affine)."""
        return len(self.term_names)

    @property
    def shape_count(self) -> int:
        """Number of scalar shape functions ``n T``."""
        return self.kernel_count * self.terms

    @property
    def dof_count(self) -> int:
        """Number of generalised coordinates ``3 n T`` (30 per kernel for Q-GMLS)."""
        return 3 * self.shape_count

    def evaluate(self, x: torch.Tensor, derivatives: int = 2) -> ShapeValues:
        """Shape functions (Eq. 7) and their exact spatial derivatives at points ``x``.

        Derivatives are analytic and exact (module docstring); the basis is centred at each point
        and scaled by the mean support radius of the kernels covering it.

        Args:
            x: ``[M, 3]`` rest positions (length).
            derivatives: 0 (values), 1 (+ gradients) or 2 (+ Hessians).

        Returns:
            :class:`ShapeValues` with ``S = A T``, ``A`` the most kernels covering any point.

        Raises:
            ValueError: a point lies outside every kernel's support, or ``G`` is singular there.
        """
        if derivatives not in (0, 1, 2):
            raise ValueError(f"derivatives must be 0, 1 or 2, got {derivatives}")
        x = as_points(x, "x").to(self.centres.device)
        kernel, active = self._active_kernels(x)
        rows = torch.arange(x.shape[0], device=x.device).split(_CHUNK)
        parts = [self._shape_jet(x[r], kernel[r], active[r], derivatives) for r in rows]
        m, a, t = x.shape[0], kernel.shape[1], self.terms
        jet = [
            torch.cat([part[order] for part in parts]).reshape(m, a * t, *([3] * order))
            for order in range(3)
            if order <= derivatives
        ]
        shape_index = kernel.unsqueeze(-1) * t + torch.arange(t, device=x.device)
        shape_index = torch.where(active.unsqueeze(-1), shape_index, -1).reshape(m, a * t)
        return ShapeValues(shape_index, *jet)

    def displacement(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Displacement ``u(x) = Σ_s N_s(x) q_s = J(x) q`` (Eq. 6, 9).

        Args:
            q: ``[n, T, 3]`` generalised coordinates (layout in the module docstring).
            x: ``[M, 3]`` rest positions.

        Returns:
            ``[M, 3]`` displacements (length).
        """
        shape = self.evaluate(x, derivatives=0)
        return torch.einsum("ms,msa->ma", shape.value, self._gather(q, shape.index))

    def deformation_gradient(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Deformation gradient ``F = I + ∇u``, ``F_ab = δ_ab + Σ_s q_s,a ∂N_s/∂x_b`` (Eq. 12).

        Args:
            q: ``[n, T, 3]`` generalised coordinates.
            x: ``[M, 3]`` rest positions.

        Returns:
            ``[M, 3, 3]`` (dimensionless).
        """
        shape = self.evaluate(x, derivatives=1)
        grad_u = torch.einsum("msb,msa->mab", shape.grad, self._gather(q, shape.index))
        return grad_u + torch.eye(3, dtype=grad_u.dtype, device=grad_u.device)

    def dense_jacobian(self, x: torch.Tensor) -> torch.Tensor:
        """Dense ``J(x) = N(x) ⊗ I3`` with ``u = J q`` for the flat ``q`` (Eq. 9); for tests and small problems.

        Args:
            x: ``[M, 3]`` rest positions.

        Returns:
            ``[M, 3, 3 n T]`` with ``J[m, a, s * 3 + b] = N_s(x_m) δ_ab``.
        """
        value = self.evaluate(x, derivatives=0).dense_value(self.shape_count)
        eye = torch.eye(3, dtype=value.dtype, device=value.device)
        return torch.einsum("ms,ab->masb", value, eye).reshape(x.shape[0], 3, 3 * self.shape_count)

    def dof_from_field(
        self,
        value: torch.Tensor,
        gradient: torch.Tensor | None = None,
        hessian: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Generalised coordinates of a displacement field sampled at the kernel centres.

        Args:
            value: ``[n, 3]`` ``u(x_i)`` (length).
            gradient: ``[n, 3, 3]`` ``∂u_a/∂x_j`` at ``x_i`` as ``[i, a, j]`` (dimensionless); ``None``
                means zero. Unused by the affine basis.
            hessian: ``[n, 3, 3, 3]`` ``∂²u_a/∂x_j∂x_k`` at ``x_i`` as ``[i, a, j, k]`` (1/length);
                ``None`` means zero. Unused by the affine basis.

        Returns:
            ``q``: ``[n, T, 3]`` float64.
        """
        n = self.kernel_count
        value = torch.as_tensor(value, dtype=torch.float64, device=self.centres.device)
        if value.shape != (n, 3):
            raise ValueError(f"value must be [n, 3] = [{n}, 3], got {tuple(value.shape)}")
        q = torch.zeros(n, self.terms, 3, dtype=torch.float64, device=self.centres.device)
        q[:, 0] = value
        if self.order == "affine":
            return q
        if gradient is not None:
            gradient = torch.as_tensor(gradient, dtype=torch.float64, device=q.device)
            if gradient.shape != (n, 3, 3):
                raise ValueError(f"gradient must be [n, 3, 3] = [{n}, 3, 3], got {tuple(gradient.shape)}")
            q[:, 1:4] = gradient.transpose(1, 2)
        if hessian is not None and self.order == "quadratic":
            hessian = torch.as_tensor(hessian, dtype=torch.float64, device=q.device)
            if hessian.shape != (n, 3, 3, 3):
                raise ValueError(f"hessian must be [n, 3, 3, 3] = [{n}, 3, 3, 3], got {tuple(hessian.shape)}")
            for t, (j, k) in enumerate(_SECOND_PAIRS, start=4):
                q[:, t] = hessian[:, :, j, k]
        return q

    def _shape_jet(
        self, x: torch.Tensor, kernel: torch.Tensor, active: torch.Tensor, derivatives: int
    ) -> tuple[torch.Tensor, ...]:
        """Shape-function jet ``[C, A, T(, 3(, 3))]`` at points ``x [C, 3]`` from their candidate kernels."""
        mask = active.to(torch.float64)
        radius = torch.where(active, self.support_radius[kernel], 1.0)
        length = (radius * mask).sum(1) / mask.sum(1)
        offset = self.centres[kernel] - x.unsqueeze(1)
        row_scale = length.unsqueeze(-1) ** (-self._term_derivative_order)
        terms = polynomial_terms(offset / length[:, None, None], self.order) * row_scale[:, None, :, None]
        jet = _mls_weight_jet(-offset, radius, derivatives)
        weight = tuple(w * mask.view(*mask.shape, *(1,) * (w.dim() - 2)) for w in jet)  # padding weighs zero
        self._check_invertible(moment_matrix(weight[0], terms))
        rows = self._basis_rows * (length.unsqueeze(-1) ** (-self._basis_row_derivative_order)).unsqueeze(-1)
        basis_at_x = (rows[:, 0], rows[:, 1:4], rows[:, self._second_rows])
        return shape_functions(weight, terms, basis_at_x[: derivatives + 1])

    def _active_kernels(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``[M, A]`` kernels whose support contains each point (nearest first) and the validity mask."""
        kernels, actives = [], []
        for chunk in x.split(_CHUNK):
            ratio = torch.cdist(chunk, self.centres, compute_mode=EXACT_CDIST) / self.support_radius
            if self.visibility is not None:
                ratio = torch.where(self.visibility(chunk, self.centres), ratio, torch.inf)
            count = int((ratio < 1.0).sum(1).max())
            nearest = ratio.topk(max(count, 1), dim=1, largest=False)
            kernels.append(nearest.indices)
            actives.append(nearest.values < 1.0)
        width = max(k.shape[1] for k in kernels)
        kernel = torch.cat([torch.nn.functional.pad(k, (0, width - k.shape[1])) for k in kernels])
        active = torch.cat([torch.nn.functional.pad(k, (0, width - k.shape[1]), value=False) for k in actives])
        uncovered = int((~active.any(1)).sum())
        if uncovered:
            raise ValueError(
                f"{uncovered} of {x.shape[0]} points lie outside the support of every kernel; "
                "use larger support radii (support_radii(centres, points) with these points) or more kernels"
                + ("; a cut may leave a piece without a kernel: place one there" if self.visibility else "")
            )
        return kernel, active

    def _check_invertible(self, gram: torch.Tensor) -> None:
        """Raise where ``G`` (Eq. 8) is numerically singular, judged on its Jacobi-scaled form ``D G D``."""
        diagonal = gram.diagonal(dim1=-2, dim2=-1)
        scale = diagonal.clamp_min(1e-300 + 1e-14 * diagonal.amax(-1, keepdim=True)).rsqrt()
        eigenvalues = torch.linalg.eigvalsh(gram * scale.unsqueeze(-1) * scale.unsqueeze(-2))
        singular = int((eigenvalues[:, 0] <= _RCOND_MIN * eigenvalues[:, -1]).sum())
        if singular:
            hint = (
                "the affine basis needs the kernel centres in each support to span 3D (not colinear or "
                "coplanar); use order='quadratic', whose derivative terms make G invertible, or more kernels"
                if self.order == "affine"
                else "check for non-finite centres or radii"
            )
            raise ValueError(f"G(x) (Eq. 8) is singular at {singular} of {gram.shape[0]} points: {hint}")

    def _gather(self, q: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """``[M, S, 3]`` DOFs of the active shape indices (padding reads shape 0, weighted by zero)."""
        q = torch.as_tensor(q, dtype=torch.float64, device=self.centres.device)
        if q.shape != (self.kernel_count, self.terms, 3):
            raise ValueError(
                f"q must be [n, T, 3] = [{self.kernel_count}, {self.terms}, 3], got {tuple(q.shape)}; "
                "reshape a flat q with q.reshape(n, T, 3)"
            )
        return q.reshape(self.shape_count, 3)[index.clamp_min(0)]


def as_points(points: torch.Tensor, name: str) -> torch.Tensor:
    """``points`` as float64 ``[N, 3]``; a ValueError naming ``name`` when the shape is another or a coordinate is
    not finite."""
    points = torch.as_tensor(points)
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3], got {tuple(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError(f"{name} contains non-finite coordinates")
    return points.to(torch.float64)
