"""The Newton system of the garment simulator: element Hessians assembled on a block pattern, and its solver.

Each Newton iteration of :class:`physavatar.cloth.SolverCloth` minimises a quadratic model of the incremental
potential: the element Hessians it gives (:class:`NewtonElement`) are PSD-filtered and scattered into a sparse
matrix of the free vertices on a block pattern that only grows (:class:`NewtonMatrices`, :mod:`kernels.assembly`),
and :class:`LinearSolver`, chosen once per simulator, solves it for the Newton direction.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from kernels import assembly, cudss, element_terms
from physavatar.cloth.config import ClothConfig

__all__ = [
    "DENSE_MAX_DOFS",
    "LinearSolver",
    "NewtonElement",
    "NewtonMatrices",
    "NewtonMatrix",
    "filtered_elements",
]

DENSE_MAX_DOFS = 30_000
"""Largest garment DOF count (3 per vertex) that ``linear_solver="auto"`` factors densely on CUDA where cuDSS is
not installed (a float64 matrix of up to 7.2 GB)."""


class NewtonElement(NamedTuple):
    """One kind of element of the incremental potential, as the Newton matrix receives it."""

    index: torch.Tensor  # [N, k] int32 vertices (garment and body)
    hess: torch.Tensor  # [N, 3k, 3k] Hessians, unscaled and unfiltered
    scale: float  # factor on each Hessian (Δt²)
    projection: str  # PSD filter: "none", "clamp" (eigenvalues at least zero) or "abs" (their absolute values)
    reach: torch.Tensor | None  # [M, k] contacts: the candidates within REACH · d̂, the active ones among them; a
    # pattern miss grows the pattern by all their blocks, so that pairs that come within d̂ later seldom change it
    exact_psd: bool = False  # filter in the Hessians' own dtype whatever eigen_dtype says (filtered_elements)


class NewtonMatrix(NamedTuple):
    """A Newton matrix of the free vertices: its block pattern and the values in the pattern's scalar CSR order."""

    pattern: assembly.BlockPattern
    values: torch.Tensor

    def to_dense(self) -> torch.Tensor:
        size = 3 * self.pattern.n
        crow = self.pattern.crow.long()
        rows = torch.repeat_interleave(torch.arange(size, device=crow.device), crow[1:] - crow[:-1])
        h = torch.zeros(size, size, dtype=self.values.dtype, device=self.values.device)
        h[rows, self.pattern.col.long()] = self.values
        return h

    def to_scipy(self) -> scipy.sparse.csc_matrix:
        """As SciPy's CSC matrix: the CSR arrays of a symmetric matrix read as CSC arrays give the same matrix."""
        size = 3 * self.pattern.n
        arrays = (self.values, self.pattern.col, self.pattern.crow)
        return scipy.sparse.csc_matrix(tuple(t.cpu().numpy() for t in arrays), shape=(size, size))


class NewtonMatrices:
    """Assembles each Newton matrix on a block pattern that only grows while the free vertices stay the same.

    The pattern starts as that of the garment's elements (membrane and bending join each vertex to its
    neighbours; body contacts add no block of their own, since only one garment vertex or one garment edge takes
    part). Self-contacts come and go: an assembly that meets a block outside the pattern (a pair of vertices joined
    for the first time) bounds it on the diagonal (:mod:`kernels.assembly`: the matrix stays SPD, its direction a
    descent direction), and the Newton loop, which reads the count of such blocks with its other flags, keeps that
    matrix and defers the growth (:meth:`defer`): at the next step's :meth:`prepare` the pattern grows by every
    block of the elements at hand and of the contact candidates within :data:`~physavatar.cloth.contact.REACH` · d̂.
    cuDSS analyses a pattern anew whenever it changes, at some 30 times the cost of a numeric factorisation
    (``docs/benchmarks.md``), so the pattern grows at most once a step and outlives the step: it restarts from the
    garment's elements only when the free vertices change or when contacts have doubled it.

    Each element kind's Hessians are PSD-filtered by one batched eigensolver call
    (:func:`kernels.element_terms.project_psd`, its decompositions in ``eigen_dtype``), then scattered by one Warp
    launch (:mod:`kernels.assembly`).
    """

    def __init__(self, elastic: list[torch.Tensor], eigen_dtype: torch.dtype | None = None):
        self.elastic = elastic
        self.eigen_dtype = eigen_dtype  # of the PSD filter's decompositions (filtered_elements)
        self.pattern: assembly.BlockPattern | None = None
        self.version = 0  # counts the patterns set
        self._mass_slots: torch.Tensor | None = None
        self.dof: torch.Tensor | None = None  # the last step's free DOFs, as begin_step was given them
        self._copy: torch.Tensor | None = None  # and their values then
        self.elastic_blocks = 0
        self._pending: list[torch.Tensor] = []  # block keys that the next step's pattern takes (:meth:`defer`)

    def _set_pattern(self, pattern: assembly.BlockPattern) -> None:
        self.pattern = pattern
        self.version += 1
        self._mass_slots = pattern.diagonal[:, [0, 1, 2], [0, 1, 2]].reshape(-1)  # each free DOF's diagonal entry

    def begin_step(self, dof: torch.Tensor, n: int) -> None:
        """The pattern for a step's free DOFs ``dof`` (``n`` free vertices): the last one, grown by the blocks
        deferred to it, if the free vertices are the same and it has not doubled, else the garment's elements'."""
        same = self._copy is not None and self._copy.shape == dof.shape and bool(torch.equal(self._copy, dof))
        if not same or self.pattern.block_col.numel() > 2 * self.elastic_blocks:
            keys = torch.cat([assembly.block_keys(index, dof, n) for index in self.elastic])
            self._set_pattern(assembly.block_pattern(keys, n))
            self.elastic_blocks = self.pattern.block_col.numel()
        elif self._pending:
            self._set_pattern(assembly.block_pattern(torch.cat([self.pattern.keys(), *self._pending]), n))
        self._pending = []
        self.dof, self._copy = dof, dof.clone()

    def prepare(self, elements: list[NewtonElement], dof: torch.Tensor, n: int) -> list[NewtonElement]:
        """The pattern for this step's free DOFs ``dof`` (``n`` free vertices; a ``dof`` tensor other than the last
        one starts a step: :meth:`begin_step`), and ``elements`` as :meth:`scatter` takes them: the non-empty ones,
        PSD-filtered (:func:`filtered_elements`)."""
        if dof is not self.dof:
            self.begin_step(dof, n)
        return filtered_elements(elements, self.eigen_dtype)

    def scatter(self, active: list[NewtonElement], rhs: torch.Tensor, dof: torch.Tensor, p_kin, mass):
        """``(NewtonMatrix, rhs [n, 3], missing)``: ``Σ`` scaled element Hessians of ``active`` (from :meth:`prepare`)
        plus ``diag(mass)`` (when given), ``rhs`` less the kinematic pushes, and the number of blocks that fell
        outside the pattern (1-element int32 tensor, left on the device: nonzero means the matrix is incomplete;
        :meth:`grow` the pattern and scatter again)."""
        p_kin = p_kin.contiguous()
        values = rhs.new_zeros(self.pattern.col.numel())
        out = rhs.clone()
        missing = torch.zeros(1, dtype=torch.int32, device=rhs.device)
        if mass is not None:
            values[self._mass_slots] = mass.repeat_interleave(3)
        for element in active:
            index, hess, scale = element.index, element.hess, element.scale
            assembly.scatter_hessians(self.pattern, values, out, missing, index, hess, dof, p_kin, scale)
        return NewtonMatrix(self.pattern, values), out, missing

    def grow(self, elements: list[NewtonElement], dof: torch.Tensor, n: int) -> None:
        """Add every block of ``elements`` and of their reach (:class:`NewtonElement`) to the pattern."""
        self._set_pattern(assembly.block_pattern(torch.cat([self.pattern.keys(), *_keys(elements, dof, n)]), n))

    def defer(self, elements: list[NewtonElement], dof: torch.Tensor, n: int) -> None:
        """:meth:`grow` at the next step's :meth:`prepare` (if the pattern does not restart then), not now. The
        garment's elements are in the pattern already: only the contacts' and friction's blocks are kept."""
        others = [e for e in elements if not any(e.index is index for index in self.elastic)]
        self._pending = [torch.unique(torch.cat([*self._pending, *_keys(others, dof, n)]))]

    def assemble(self, elements: list[NewtonElement], rhs: torch.Tensor, dof: torch.Tensor, p_kin, mass):
        """``(NewtonMatrix, rhs [n, 3])`` of :meth:`scatter`, the pattern grown until it holds every block."""
        return self.complete(self.prepare(elements, dof, rhs.shape[0]), elements, rhs, dof, p_kin, mass)

    def complete(self, active: list[NewtonElement], elements: list[NewtonElement], rhs: torch.Tensor, dof, p_kin, mass):
        """:meth:`assemble` from the prepared ``active`` elements: :meth:`scatter` them, :meth:`grow` the pattern by
        ``elements`` (from which they were prepared) while blocks fall outside it, and scatter again."""
        while True:
            matrix, out, missing = self.scatter(active, rhs, dof, p_kin, mass)
            if int(missing) == 0:
                return matrix, out
            self.grow(elements, dof, rhs.shape[0])


def _keys(elements: list[NewtonElement], dof: torch.Tensor, n: int) -> list[torch.Tensor]:
    """The block keys of ``elements`` and of their reach (:class:`NewtonElement`)."""
    return [assembly.block_keys(e.index if e.reach is None else e.reach, dof, n) for e in elements]


def filtered_elements(elements: list[NewtonElement], eigen_dtype: torch.dtype | None = None) -> list[NewtonElement]:
    """The non-empty ``elements`` with their Hessians PSD-filtered (``eigen_dtype``: the decompositions' dtype, as
    :func:`kernels.element_terms.project_psd` takes it).

    One batched eigensolver call per element kind: one call over bending and contact Hessians together (contact
    Hessians many orders of magnitude stiffer than the bending's) slowed cuSOLVER's batched ``syevd`` down
    (``docs/benchmarks.md``).

    Elements marked ``exact_psd`` (the barrier's) are decomposed in their own dtype. A barrier Hessian near contact is
    a huge stiffness along the pair's normal over modest ones across it; float32 Jacobi's error, relative to the
    largest eigenvalue, then lands on the small ones and stiffens the directions in which the garment should slide:
    on CUDA the 160-vertex skirt's walk stalled for 50 Newton iterations at pairs 10⁻¹³ m apart, where float64
    filtering converges."""
    out = []
    for element in elements:
        if not element.index.shape[0]:
            continue
        if element.projection != "none":
            dtype = None if element.exact_psd else eigen_dtype
            hess = element_terms.project_psd(element.hess, element.projection == "abs", dtype)
            element = element._replace(hess=hess, projection="none")
        out.append(element)
    return out


class LinearSolver:
    """Solves the Newton systems of one simulator with the linear solver its configuration names, chosen once.

    ``config.linear_solver``: ``"direct"`` (SuperLU on the host), ``"cudss"`` (cuDSS's sparse Cholesky), ``"dense"``
    (dense Cholesky on the device) or ``"cg"`` (block-Jacobi CG); ``"auto"`` takes direct on the CPU and on CUDA
    cuDSS where it loads, else dense up to :data:`DENSE_MAX_DOFS` garment DOFs and CG beyond
    (:class:`~physavatar.cloth.config.ClothConfig`).

    Args:
        config: the linear solver's name and CG's tolerance and iteration cap.
        device: the device the systems live on.
        vertex_count: the garment's vertices (3 DOFs each).

    Raises:
        kernels.cudss.CudssError: ``"cudss"`` where cuDSS cannot load.
    """

    def __init__(self, config: ClothConfig, device: torch.device, vertex_count: int):
        self.config = config
        v = vertex_count
        solver = config.linear_solver
        if solver == "auto":
            if device.type != "cuda":
                solver = "direct"
            elif cudss.available():
                solver = "cudss"
            else:
                solver = "dense" if 3 * v <= DENSE_MAX_DOFS else "cg"
        self._cudss = cudss.SparseSPDSolver(device) if solver == "cudss" else None  # raises where cuDSS cannot load
        self._unchecked = False  # the last solve queued an unchecked cuDSS factorisation (:meth:`solved`)
        self.kind = solver  # the linear solver chosen: "direct", "cudss", "dense" or "cg"

    def solve(self, matrix: NewtonMatrix, rhs: torch.Tensor, wait: bool = True) -> torch.Tensor:
        """Solve ``H p = rhs`` for the free DOFs (``H`` SPD; ``rhs`` ``[3n]`` or ``[3n, P]``).

        With ``wait`` False, cuDSS's factorisation is not checked before its solve is queued: :meth:`solved` says
        afterwards whether the result holds (a failed factorisation leaves garbage, which the check then catches).
        """
        self._unchecked = False
        n = matrix.pattern.n
        if n == 0:
            return rhs.new_zeros(rhs.shape)
        if rhs.dim() == 2 and self.kind == "cg":
            return torch.stack([self.solve(matrix, rhs[:, j]) for j in range(rhs.shape[1])], 1)
        if self.kind == "dense":
            return _dense_solve(matrix, rhs)
        if self.kind == "cudss":
            pattern = matrix.pattern
            if not wait:
                self._cudss.queue_factor(pattern.crow, pattern.col, matrix.values)
                self._unchecked = True
            elif not self._cudss.factor(pattern.crow, pattern.col, matrix.values):
                return _dense_solve(matrix, rhs)
            return self._cudss.solve(rhs)
        if self.kind == "direct":
            return torch.from_numpy(_sparse_spd_solve(matrix.to_scipy(), rhs.cpu().numpy())).to(rhs.device)
        return _block_jacobi_cg(matrix, rhs, self.config.cg_tolerance, self.config.cg_max_iterations)

    def solved(self) -> bool:
        """Whether the last :meth:`solve` holds (only an unchecked cuDSS factorisation can fail silently)."""
        return not self._unchecked or self._cudss.positive_definite()


def _sparse_spd_solve(h: scipy.sparse.csc_matrix, rhs):
    """Solve ``h x = rhs`` for a sparse SPD ``h`` by SuperLU with a symmetric ordering and diagonal pivots.

    The fill-reducing ordering of ``hᵀ + h`` only pays off if the factorisation keeps to the diagonal: with
    SuperLU's default threshold pivoting it swaps rows of this matrix, loses the ordering and fills in, several times
    slower (``docs/benchmarks.md``). An SPD matrix needs no pivoting, so the diagonal pivot
    threshold is 0 (a Cholesky-like LDU); should a pivot vanish in floating point, the solve is repeated with
    SuperLU's partial pivoting.
    """
    try:
        lu = scipy.sparse.linalg.splu(
            h, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        x = lu.solve(rhs)
        if np.isfinite(x).all():
            return x
    except RuntimeError:  # "Factor is exactly singular"
        pass
    return scipy.sparse.linalg.splu(h, permc_spec="COLAMD").solve(rhs)


def _dense_solve(matrix: NewtonMatrix, rhs: torch.Tensor) -> torch.Tensor:
    """Solve ``H x = rhs`` densely on the device: Cholesky, or LU where ``H`` is not positive definite (the exact
    Hessians of a sensitivity step may not be)."""
    h = matrix.to_dense()
    factor, info = torch.linalg.cholesky_ex(h)
    column = rhs if rhs.dim() == 2 else rhs[:, None]
    x = torch.cholesky_solve(column, factor) if int(info) == 0 else torch.linalg.solve(h, column)
    return x if rhs.dim() == 2 else x[:, 0]


def _block_jacobi_cg(matrix: NewtonMatrix, rhs: torch.Tensor, tol: float, max_iterations: int) -> torch.Tensor:
    """Conjugate gradients on the sparse SPD ``H`` with the inverse 3×3 diagonal blocks as preconditioner."""
    pattern, values = matrix
    n = pattern.n
    with warnings.catch_warnings():  # "sparse CSR support is in beta": mv on CSR is all this needs
        warnings.simplefilter("ignore", UserWarning)
        h = torch.sparse_csr_tensor(pattern.crow, pattern.col, values, (3 * n, 3 * n), check_invariants=False)
    d_inv = torch.linalg.inv(values[pattern.diagonal])

    def precondition(res: torch.Tensor) -> torch.Tensor:
        return torch.bmm(d_inv, res.view(n, 3, 1)).reshape(-1)

    x = torch.zeros_like(rhs)
    res = rhs.clone()
    z = precondition(res)
    p = z.clone()
    rz = torch.dot(res, z)
    stop = tol * tol * float(torch.dot(rhs, rhs))
    for k in range(max_iterations):
        hp = torch.mv(h, p)
        step = rz / torch.dot(p, hp)
        x += step * p
        res -= step * hp
        # the residual test reads the device's value back: every 8th iteration, so a GPU is not stalled each time
        if k % 8 == 7 and float(torch.dot(res, res)) <= stop:
            break
        z = precondition(res)
        rz_next = torch.dot(res, z)
        p = z + (rz_next / rz) * p
        rz = rz_next
    return x
