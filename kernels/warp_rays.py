"""Ray-sample warping from the deformed scene back to the rest NeRF (PIE-NeRF §4.6, Eq. 19–21; Fig. 8).

A sample x̃ on a camera ray through the deformed scene must be looked up in the NeRF at its rest position x,
with x̃ = x + u(x). Near an integrator point (IP) with rest position x_k, deformed position x̃_k = x_k + u(x_k),
deformation gradient F_k = I + ∇u(x_k) and its gradient ∇F_k (``∇F[k, a, b, c] = ∂F_ab/∂x_c``), the
second-order Taylor expansion of x̃(x) = x + u(x) about x_k, written in d = x − x_k, is

    x̃ − x̃_k = F_k d + ½ ∇F_k : (d ⊗ d),     (½ ∇F_k : d d)_a = ½ Σ_bc ∇F[k, a, b, c] d_b d_c.

This is Eq. 19 with consistent signs. The paper writes ``x̃ − x̃_k = u(x) − u(x_k) ≈ ∇u(x_k)(x_k − x) +
½(∇F(x_k)·(x_k − x))·(x_k − x)``; but x̃ − x̃_k = d + u(x) − u(x_k), which turns ∇u_k into F_k = I + ∇u_k, and
the Taylor series of u in d = x − x_k has ``+∇u_k d`` (the linear term changes sign with d ↦ −d, the quadratic
term does not). The paper's Eq. 20–21 rearrange the quadratic as ``A(x) x = b`` in the absolute position x;
here the same root is found in the offset d, which keeps the numbers small (float32) and the start at zero.

Solve (Eq. 20). Newton's method on r(d) = F_k d + ½ ∇F_k : d d − (x̃ − x̃_k), starting at x = x_k (d = 0), as
the paper does. The Jacobian is J(d) = F_k + ∇F_k^sym · d with ``∇F^sym[a, b, c] = ½(∇F[a, b, c] + ∇F[a, c, b])``,
and each iteration solves the 3×3 system J Δ = −r by the adjugate. Because r(0) = −(x̃ − x̃_k) and J(0) = F_k,
the first iterate is exactly the first-order (linear) warp d = F_k⁻¹ (x̃ − x̃_k) of most NeRF editors, which is
the ``quadratic=False`` mode (Fig. 8, left); the further iterations add the quadratic correction.

Convergence. Convergence is quadratic once the iterate is near the root; the iteration stops when the update
is shorter than ``tolerance`` (metres). Rendering the bent teapot rod of ``tests/pienerf/test_render.py`` (tip
dragged 30 cm sideways, IPs 10–15 cm apart along the rod), 94 % of the 90k warped samples stopped after 3
iterations (the linear step, one quadratic correction, one update below 1 µm), none needed more than 7 and
none fell back; the paper reports "within tens of iterations". Two cases fall back to the linear warp:

* the Jacobian is singular, ``|det J| < 1e-6`` (J is dimensionless, ≈ 1 for moderate strain): the quadratic
  map folds over there and has no unique inverse; if F_k itself is singular (a collapsed IP, which the
  Neo-Hookean solver never produces) the linear warp does not exist either and the IP contributes a pure
  translation, u(x) ≈ u(x_k);
* no convergence within ``iterations`` (x̃ lies outside the range of the local quadratic, e.g. beyond a fold).

Blending. Each of the three nearest deformed IPs gives a displacement estimate u_k(x̃) = x̃ − x = (x̃_k − x_k) +
(x̃ − x̃_k) − d; the estimates are averaged with inverse-distance weights 1 / ‖x̃ − x̃_k‖ (§4.6) and
x = x̃ − ū. Blending displacements (not positions) makes the identity exact: with q = 0 every IP has zero
displacement, F = I and ∇F = 0, Newton returns d = x̃ − x̃_k bit for bit, every estimate is exactly 0 and the
warp returns x̃ unchanged, so an undeformed scene renders exactly as the NeRF does.

Empty space. A sample whose nearest deformed IP is farther than that IP's cutoff radius is marked invalid
(the renderer gives it σ = 0): the Taylor expansions mean nothing there.

Framework: Taichi, one sample per thread with a data-dependent Newton loop: the project's rule for per-sample
rendering kernels that must run interactively on a CPU (Taichi uses every core, Warp's CPU backend one).
Timings against the torch reference (:mod:`kernels.reference.warp_rays`): ``docs/benchmarks.md``.

A renderer's round (:func:`warp_round`) takes the marched samples in their per-ray slots, finds each one's nearest
IPs, warps it and tests its rest cell in one call. It is kept in Warp too (``framework=``, the default on CUDA, where
a Taichi launch costs the host several times a Warp one; :func:`kernels.backend.default_framework`): a search kernel
and a warp kernel over all the round's slots, so nothing is compacted first and the round needs one host sync. On
one kernel doing both is slower, as the search then runs at the Newton solve's lower occupancy
(``docs/benchmarks.md``).
"""

# Warp needs int(0)/float(0.0) to declare variables that change inside dynamic loops.
# ruff: noqa: UP018

from typing import NamedTuple

import taichi as ti
import torch
import warp as wp

from kernels import backend
from kernels.spatial_hash import SpatialHash, knn3_exhaustive_row, knn_row

wp.set_module_options({"enable_backward": False})  # rendering kernels: forward only, no adjoints to compile

__all__ = ["EXHAUSTIVE_IPS", "SINGULAR_DETERMINANT", "WarpedSamples", "splat_occupancy", "warp_round", "warp_to_rest"]

SINGULAR_DETERMINANT = 1e-6
"""``|det J|`` below which a Newton Jacobian (dimensionless) counts as singular."""

EXHAUSTIVE_IPS = 512
"""Up to this many IPs a round finds each sample's 3 nearest by measuring every IP instead of through the hash grid,
which is the faster there (``docs/benchmarks.md``, ``kernels.warp_rays``)."""

_MIN_DISTANCE = 1e-12  # metres; a sample exactly on an IP gets weight 1 / this instead of 1 / 0


@ti.func
def _solve3_ti(J, rhs):
    """Solve ``J x = rhs`` (3×3) by the adjugate; returns ``(x, det)``, x = 0 when singular."""
    c00 = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
    c01 = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
    c02 = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
    det = J[0, 0] * c00 + J[0, 1] * c01 + J[0, 2] * c02
    x = ti.math.vec3(0.0)
    if ti.abs(det) >= SINGULAR_DETERMINANT:
        adj = ti.math.mat3(
            c00, J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2], J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1],
            c01, J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0], J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2],
            c02, J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1], J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0],
        )
        x = (adj @ rhs) / det
    return x, det


@ti.func
def _taylor_offset_ti(grad_F: ti.template(), k, F, b, quadratic: ti.template(), iterations, tolerance):
    """Rest offset d = x − x_k with x̃ − x̃_k = b (Eq. 19–20); returns ``(d, newton iterations, fell back)``."""
    # First Newton step from d = 0 is the linear warp d = F⁻¹ b.
    d, det = _solve3_ti(F, b)
    used = 1
    fallback = 0
    if ti.abs(det) < SINGULAR_DETERMINANT:
        d = b  # collapsed IP: pure translation, u(x) ≈ u(x_k)
        fallback = 1
    elif ti.static(quadratic):
        linear = d
        converged = 0
        while used < iterations and converged == 0:
            quad = ti.math.vec3(0.0)
            J = F
            for a in ti.static(range(3)):
                for c in ti.static(range(3)):
                    for e in ti.static(range(3)):
                        g = grad_F[k, a, c, e]
                        quad[a] += 0.5 * g * d[c] * d[e]
                        J[a, c] += 0.5 * g * d[e]
                        J[a, e] += 0.5 * g * d[c]
            residual = F @ d + quad - b
            step, det_J = _solve3_ti(J, -residual)
            if ti.abs(det_J) < SINGULAR_DETERMINANT:
                break
            d += step
            used += 1
            if step.norm_sqr() <= tolerance * tolerance:
                converged = 1
        if converged == 0:
            d = linear
            fallback = 1
    return d, used, fallback


@ti.kernel
def _warp_ti(
    samples: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    neighbours: ti.types.ndarray(dtype=ti.i32, ndim=2),
    distances: ti.types.ndarray(dtype=ti.f32, ndim=2),
    ip_deformed: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    ip_displacement: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    F: ti.types.ndarray(dtype=ti.math.mat3, ndim=1),
    grad_F: ti.types.ndarray(dtype=ti.f32, ndim=4),
    cutoff: ti.types.ndarray(dtype=ti.f32, ndim=1),
    quadratic: ti.template(),
    iterations: ti.i32,
    tolerance: ti.f32,
    rest: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    valid: ti.types.ndarray(dtype=ti.u8, ndim=1),
    newton_iterations: ti.types.ndarray(dtype=ti.i32, ndim=1),
    fallback: ti.types.ndarray(dtype=ti.u8, ndim=1),
):
    for s in range(samples.shape[0]):
        x_tilde = samples[s]
        nearest = neighbours[s, 0]
        inside = 0
        if nearest >= 0:
            if distances[s, 0] <= cutoff[nearest]:
                inside = 1
        position = x_tilde
        most = 0
        fell_back = 0
        if inside == 1:
            u_sum = ti.math.vec3(0.0)
            w_sum = 0.0
            for j in range(neighbours.shape[1]):
                k = neighbours[s, j]
                if k >= 0:
                    b = x_tilde - ip_deformed[k]
                    d, used, fb = _taylor_offset_ti(grad_F, k, F[k], b, quadratic, iterations, tolerance)
                    w = 1.0 / ti.max(distances[s, j], _MIN_DISTANCE)
                    u_sum += w * (ip_displacement[k] + (b - d))
                    w_sum += w
                    most = ti.max(most, used)
                    fell_back = ti.max(fell_back, fb)
            position = x_tilde - u_sum / w_sum
        rest[s] = position
        valid[s] = ti.cast(inside, ti.u8)
        newton_iterations[s] = most
        fallback[s] = ti.cast(fell_back, ti.u8)


class WarpedSamples(NamedTuple):
    """Rest positions of deformed-space samples.

    Attributes:
        rest: float32 ``[S, 3]`` rest positions x, metres (x̃ itself where ``valid`` is False).
        valid: bool ``[S]``: the nearest deformed IP lies within its cutoff (else the sample is empty space).
        iterations: int32 ``[S]``: most Newton iterations any neighbour took (1 = the linear step; 0 invalid).
        fallback: bool ``[S]``: some neighbour fell back to the linear warp (singular Jacobian or no
            convergence; module docstring).
    """

    rest: torch.Tensor
    valid: torch.Tensor
    iterations: torch.Tensor
    fallback: torch.Tensor


def warp_to_rest(
    samples: torch.Tensor,
    neighbours: torch.Tensor,
    distances: torch.Tensor,
    ip_deformed: torch.Tensor,
    ip_displacement: torch.Tensor,
    F: torch.Tensor,
    grad_F: torch.Tensor,
    cutoff: torch.Tensor,
    *,
    quadratic: bool = True,
    iterations: int = 10,
    tolerance: float = 1e-6,
) -> WarpedSamples:
    """Warp deformed-space samples to rest positions by quadratic (or linear) Taylor inversion (Eq. 19–21).

    Args:
        samples: float32 ``[S, 3]`` deformed positions x̃, metres.
        neighbours: int32 ``[S, N]`` the N (PIE-NeRF: 3) nearest deformed IPs of each sample, nearest first,
            -1 padded (:meth:`kernels.spatial_hash.SpatialHash.knn` on ``ip_deformed``).
        distances: float32 ``[S, N]`` ``‖x̃ − x̃_k‖`` to them, metres (``inf`` where padded).
        ip_deformed: float32 ``[K, 3]`` deformed IP positions x̃_k, metres.
        ip_displacement: float32 ``[K, 3]`` IP displacements u(x_k) = x̃_k − x_k, metres (formed in float64 before
            rounding, so that zero deformation gives exact zeros).
        F: float32 ``[K, 3, 3]`` deformation gradients at the IPs (Eq. 12).
        grad_F: float32 ``[K, 3, 3, 3]`` ``∂F_ab/∂x_c`` at the IPs (Eq. 15), per metre.
        cutoff: float32 ``[K]`` radius (metres) beyond which an IP is too far to warp a sample; a sample
            whose nearest IP is beyond it is invalid.
        quadratic: Newton on the quadratic expansion (Eq. 20); ``False``: the first-order warp
            x = x_k + F_k⁻¹ (x̃ − x̃_k) (Fig. 8).
        iterations: most Newton iterations (the first is the linear step).
        tolerance: stop when a Newton update is shorter than this, metres.

    Returns:
        :class:`WarpedSamples`.
    """
    count, width = _check_warp_arguments(samples, neighbours, distances, ip_deformed, ip_displacement, F, grad_F,
                                         cutoff)
    if iterations < 1 or not tolerance > 0.0:
        raise ValueError(f"need iterations >= 1 and tolerance > 0 metres, got {iterations} and {tolerance}")
    device = samples.device
    rest = torch.empty(count, 3, device=device)
    valid = torch.empty(count, dtype=torch.uint8, device=device)
    used = torch.empty(count, dtype=torch.int32, device=device)
    fallback = torch.empty(count, dtype=torch.uint8, device=device)
    if count > 0 and width > 0:
        inputs = (samples, neighbours, distances, ip_deformed, ip_displacement, F, grad_F, cutoff)
        _warp_ti(
            *(backend.taichi_arg(t.contiguous()) for t in inputs),
            bool(quadratic), int(iterations), float(tolerance),
            *(backend.taichi_arg(t) for t in (rest, valid, used, fallback)),
        )
    elif count > 0:
        rest.copy_(samples)
        valid.zero_()
        used.zero_()
        fallback.zero_()
    return WarpedSamples(rest, valid.bool(), used, fallback.bool())


# ---------------------------------------------------------------------------------------------------
# A renderer's round in Warp: nearest IPs, warp and the rest-occupancy test over a round's slots
# ---------------------------------------------------------------------------------------------------

_SINGULAR_WP = wp.constant(SINGULAR_DETERMINANT)
_MIN_DISTANCE_WP = wp.constant(_MIN_DISTANCE)


@wp.func
def _solve3_wp(J: wp.mat33, rhs: wp.vec3):
    """:func:`_solve3_ti`: ``J x = rhs`` by the adjugate; ``(x, det)``, x = 0 when singular."""
    c00 = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
    c01 = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
    c02 = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
    det = J[0, 0] * c00 + J[0, 1] * c01 + J[0, 2] * c02
    x = wp.vec3(0.0)
    if wp.abs(det) >= _SINGULAR_WP:
        adj = wp.mat33(
            c00, J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2], J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1],
            c01, J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0], J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2],
            c02, J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1], J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0],
        )
        x = (adj * rhs) / det
    return x, det


@wp.func
def _taylor_offset_wp(
    grad_F: wp.array4d(dtype=wp.float32), k: int, F: wp.mat33, b: wp.vec3, quadratic: bool, iterations: int,
    tolerance: float,
):
    """:func:`_taylor_offset_ti`: rest offset d with x̃ − x̃_k = b; ``(d, newton iterations, fell back)``."""
    d, det = _solve3_wp(F, b)
    used = int(1)
    fallback = int(0)
    if wp.abs(det) < _SINGULAR_WP:
        d = b
        fallback = 1
    elif quadratic:
        linear = d
        converged = int(0)
        while used < iterations and converged == 0:
            quad = wp.vec3(0.0)
            J = F
            for a in range(3):
                for c in range(3):
                    for e in range(3):
                        g = grad_F[k, a, c, e]
                        quad[a] = quad[a] + 0.5 * g * d[c] * d[e]
                        J[a, c] = J[a, c] + 0.5 * g * d[e]
                        J[a, e] = J[a, e] + 0.5 * g * d[c]
            residual = F * d + quad - b
            step, det_J = _solve3_wp(J, -residual)
            if wp.abs(det_J) < _SINGULAR_WP:
                break
            d = d + step
            used += 1
            if wp.length_sq(step) <= tolerance * tolerance:
                converged = 1
        if converged == 0:
            d = linear
            fallback = 1
    return d, used, fallback


@wp.kernel
def _round_neighbours_wp(
    samples: wp.array(dtype=wp.vec3),
    counts: wp.array(dtype=wp.int32),
    per_ray: int,
    grid: wp.uint64,
    ip_deformed: wp.array(dtype=wp.vec3),
    start_radius: float,
    max_radius: float,
    exhaustive: int,
    neighbours: wp.array2d(dtype=wp.int32),
    distances: wp.array2d(dtype=wp.float32),
):
    """The nearest deformed IPs of every filled slot of a round (:func:`knn_row`; ``exhaustive``: by
    :func:`knn3_exhaustive_row`, the same rows)."""
    s = wp.tid()
    if s % per_ray < counts[s // per_ray]:
        if exhaustive != 0:
            knn3_exhaustive_row(ip_deformed, samples[s], max_radius, neighbours, distances, s)
        else:
            knn_row(grid, ip_deformed, samples[s], start_radius, max_radius, neighbours, distances, s)


@wp.kernel
def _warp_round_wp(
    samples: wp.array(dtype=wp.vec3),
    counts: wp.array(dtype=wp.int32),
    per_ray: int,
    neighbours: wp.array2d(dtype=wp.int32),
    distances: wp.array2d(dtype=wp.float32),
    ip_deformed: wp.array(dtype=wp.vec3),
    ip_displacement: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    grad_F: wp.array4d(dtype=wp.float32),
    cutoff: wp.array(dtype=wp.float32),
    quadratic: bool,
    iterations: int,
    tolerance: float,
    occupancy: wp.array3d(dtype=wp.uint8),
    lo: wp.vec3,
    hi: wp.vec3,
    rest: wp.array(dtype=wp.vec3),
    keep: wp.array(dtype=wp.uint8),
):
    """One filled slot of a round: :func:`_warp_ti`'s blend of its nearest IPs' Taylor inversions, and whether the
    rest position lies in an occupied rest cell (the search is :func:`_round_neighbours_wp`; module docstring)."""
    s = wp.tid()
    x_tilde = samples[s]
    position = wp.vec3(0.0)
    kept = wp.uint8(0)
    if s % per_ray < counts[s // per_ray]:
        position = x_tilde
        nearest = neighbours[s, 0]
        if nearest >= 0:
            if distances[s, 0] <= cutoff[nearest]:
                u_sum = wp.vec3(0.0)
                w_sum = float(0.0)
                for j in range(neighbours.shape[1]):
                    k = neighbours[s, j]
                    if k >= 0:
                        b = x_tilde - ip_deformed[k]
                        d, used, fb = _taylor_offset_wp(grad_F, k, F[k], b, quadratic, iterations, tolerance)
                        w = 1.0 / wp.max(distances[s, j], _MIN_DISTANCE_WP)
                        u_sum = u_sum + w * (ip_displacement[k] + (b - d))
                        w_sum = w_sum + w
                position = x_tilde - u_sum / w_sum
                resolution = wp.vec3i(occupancy.shape[0], occupancy.shape[1], occupancy.shape[2])
                cells = wp.vec3(float(resolution[0]), float(resolution[1]), float(resolution[2]))
                cell_size = wp.cw_div(hi - lo, cells)
                u = wp.cw_div(position - lo, cell_size)
                cell = wp.vec3i(int(wp.floor(u[0])), int(wp.floor(u[1])), int(wp.floor(u[2])))
                if cell[0] >= 0 and cell[1] >= 0 and cell[2] >= 0:
                    if cell[0] < resolution[0] and cell[1] < resolution[1] and cell[2] < resolution[2]:
                        kept = occupancy[cell[0], cell[1], cell[2]]
    rest[s] = position
    keep[s] = wp.where(kept != wp.uint8(0), wp.uint8(1), wp.uint8(0))


def warp_round(
    samples: torch.Tensor,
    counts: torch.Tensor,
    ip_hash: SpatialHash,
    ip_displacement: torch.Tensor,
    F: torch.Tensor,
    grad_F: torch.Tensor,
    cutoff: torch.Tensor,
    rest_occupancy: torch.Tensor,
    rest_aabb,
    *,
    max_radius: float,
    neighbours: int = 3,
    quadratic: bool = True,
    iterations: int = 10,
    tolerance: float = 1e-6,
    framework: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp a renderer's round of marched samples to rest and tell which are worth a NeRF query.

    For every filled slot: its ``neighbours`` nearest deformed IPs (:meth:`SpatialHash.knn`), the blended Taylor
    inversion of :func:`warp_to_rest`, and the test that the rest position lies in an occupied cell of the rest
    occupancy grid (outside it σ = 0, as outside every IP's reach). With ``framework="warp"`` (the default on CUDA)
    this is two kernels (search; warp and test) over all ``A · k`` slots, empty ones included, so nothing is
    compacted or gathered first;
    ``"taichi"`` gathers the filled slots, runs :meth:`SpatialHash.knn` and :func:`warp_to_rest`'s Taichi kernel,
    and scatters back.

    Args:
        samples: float32 ``[A, k, 3]`` deformed positions; ray ``i`` filled slots ``[i, :counts[i]]``
            (:class:`kernels.volume_render.RoundSamples`).
        counts: int32 ``[A]``.
        ip_hash: :class:`SpatialHash` over the deformed IP positions x̃_k (float32 ``[K, 3]``).
        ip_displacement, F, grad_F, cutoff: as :func:`warp_to_rest`.
        rest_occupancy: uint8 or bool ``[Gx, Gy, Gz]`` rest occupancy grid over ``rest_aabb`` (``[2, 3]``, metres).
        max_radius: the nearest IPs are searched within this, metres.
        neighbours, quadratic, iterations, tolerance: as :func:`warp_to_rest` (``neighbours``: N).
        framework: ``"taichi"`` or ``"warp"``; ``None``: :func:`kernels.backend.default_framework`.

    Returns:
        ``(rest, keep)``: float32 ``[A · k, 3]`` rest positions (the sample itself where no IP reaches it, zeros in
        empty slots) and bool ``[A · k]``: filled, reached by an IP and in an occupied rest cell.
    """
    framework = backend.check_framework(framework)
    if samples.dtype != torch.float32 or samples.dim() != 3 or samples.shape[2] != 3:
        raise ValueError(f"samples must be float32 [A, k, 3], got {samples.dtype} {list(samples.shape)}")
    rays, k = samples.shape[:2]
    if counts.dtype != torch.int32 or counts.shape != (rays,):
        raise ValueError(f"counts must be int32 [A] = [{rays}], got {counts.dtype} {list(counts.shape)}")
    if neighbours < 1 or iterations < 1 or not tolerance > 0.0 or not max_radius > 0.0:
        raise ValueError(
            "need neighbours >= 1, iterations >= 1, tolerance > 0 and max_radius > 0, got "
            f"{neighbours}, {iterations}, {tolerance} and {max_radius}"
        )
    _check_ips(ip_hash.points, ip_displacement, F, grad_F, cutoff)
    grid = rest_occupancy.to(torch.uint8).contiguous()
    box = torch.as_tensor(rest_aabb, dtype=torch.float32).cpu()
    if grid.dim() != 3 or box.shape != (2, 3) or not bool((box[1] > box[0]).all()):
        raise ValueError("rest_occupancy must be a [Gx, Gy, Gz] grid over rest_aabb [2, 3] (lo, hi with hi > lo)")
    device = samples.device
    slots = rays * k
    if framework == "warp":
        rest = torch.empty(slots, 3, device=device)
        keep = torch.empty(slots, dtype=torch.uint8, device=device)
        if slots > 0:
            near = torch.empty(slots, neighbours, dtype=torch.int32, device=device)
            distance = torch.empty(slots, neighbours, device=device)
            flat = backend.warp_arg(samples.contiguous().view(-1, 3), dtype=wp.vec3)
            filled = backend.warp_arg(counts.contiguous())
            wp.launch(
                _round_neighbours_wp,
                dim=slots,
                inputs=[
                    flat,
                    filled,
                    k,
                    ip_hash.grid_id,
                    ip_hash.points_warp,
                    ip_hash.start_radius(neighbours, max_radius),
                    float(max_radius),
                    int(neighbours == 3 and ip_hash.points.shape[0] <= EXHAUSTIVE_IPS),
                    backend.warp_arg(near),
                    backend.warp_arg(distance),
                ],
                device=backend.warp_device(),
            )
            wp.launch(
                _warp_round_wp,
                dim=slots,
                inputs=[
                    flat,
                    filled,
                    k,
                    backend.warp_arg(near),
                    backend.warp_arg(distance),
                    ip_hash.points_warp,
                    backend.warp_arg(ip_displacement.contiguous(), dtype=wp.vec3),
                    backend.warp_arg(F.contiguous(), dtype=wp.mat33),
                    backend.warp_arg(grad_F.contiguous()),
                    backend.warp_arg(cutoff.contiguous()),
                    bool(quadratic),
                    int(iterations),
                    float(tolerance),
                    backend.warp_arg(grid),
                    wp.vec3(box[0].tolist()),
                    wp.vec3(box[1].tolist()),
                    backend.warp_arg(rest, dtype=wp.vec3),
                    backend.warp_arg(keep),
                ],
                device=backend.warp_device(),
            )
        return rest, keep.bool()
    filled = (torch.arange(k, device=device) < counts[:, None]).view(-1)
    index = torch.nonzero(filled).view(-1)
    positions = samples.reshape(-1, 3)[index].contiguous()
    near, distance = ip_hash.knn(positions, neighbours, max_radius=max_radius)
    warped = warp_to_rest(
        positions, near, distance, ip_hash.points, ip_displacement, F, grad_F, cutoff,
        quadratic=quadratic, iterations=iterations, tolerance=tolerance,
    )
    rest = torch.zeros(slots, 3, device=device)
    keep = torch.zeros(slots, dtype=torch.bool, device=device)
    rest[index] = warped.rest
    keep[index] = warped.valid & _occupied(warped.rest, grid, box.to(device))
    return rest, keep


def _occupied(x: torch.Tensor, grid: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """bool ``[N]``: points ``x`` in an occupied cell of ``grid`` over ``box`` (False outside it), with the Warp
    kernel's arithmetic."""
    resolution = torch.tensor(grid.shape, device=x.device)
    cell = torch.floor((x - box[0]) / ((box[1] - box[0]) / resolution.float())).long()
    inside = ((cell >= 0) & (cell < resolution)).all(-1)
    cell = torch.minimum(cell.clamp_min(0), resolution - 1)
    return inside & (grid[cell[:, 0], cell[:, 1], cell[:, 2]] != 0)


# ---------------------------------------------------------------------------------------------------
# Forward warp of occupied rest cells (the deformed occupancy grid a renderer marches through)
# ---------------------------------------------------------------------------------------------------


@wp.kernel
def _splat_occupancy_wp(
    cells_lo: wp.array(dtype=wp.vec3d),
    cell_size: wp.vec3d,
    nearest_ip: wp.array(dtype=wp.int64),
    ip_rest: wp.array(dtype=wp.vec3d),
    ip_displacement: wp.array(dtype=wp.vec3d),
    F: wp.array(dtype=wp.mat33d),
    grad_F: wp.array4d(dtype=wp.float64),
    lo: wp.vec3d,
    deformed_cell: wp.vec3d,
    grid: wp.array3d(dtype=wp.uint8),
):
    """One occupied rest cell: its eight corners moved by the quadratic map about its nearest rest IP, and every
    deformed cell their box overlaps (shrunk by 1e-4 of a cell, at most 3 per axis) marked."""
    c = wp.tid()
    k = int(nearest_ip[c])
    strain = F[k] - wp.identity(n=3, dtype=wp.float64)
    low = wp.vec3d(wp.float64(1e300), wp.float64(1e300), wp.float64(1e300))
    high = -low
    for corner in range(8):
        x = cells_lo[c] + wp.cw_mul(
            wp.vec3d(wp.float64((corner >> 2) & 1), wp.float64((corner >> 1) & 1), wp.float64(corner & 1)), cell_size
        )
        d = x - ip_rest[k]
        moved = x + ip_displacement[k] + strain * d
        for a in range(3):
            quad = wp.float64(0.0)
            for b in range(3):
                for e in range(3):
                    quad += grad_F[k, a, b, e] * d[b] * d[e]
            moved[a] = moved[a] + wp.float64(0.5) * quad
        low = wp.min(low, moved)
        high = wp.max(high, moved)
    margin = wp.float64(1e-4) * deformed_cell
    first = wp.vec3i(0)
    last = wp.vec3i(0)
    for a in range(3):
        first[a] = int(wp.floor((low[a] - lo[a] + margin[a]) / deformed_cell[a]))
        last[a] = wp.min(int(wp.floor((high[a] - lo[a] - margin[a]) / deformed_cell[a])), first[a] + 2)
        first[a] = wp.max(first[a], 0)
        last[a] = wp.min(last[a], grid.shape[a] - 1)
    for i in range(first[0], last[0] + 1):
        for j in range(first[1], last[1] + 1):
            for m in range(first[2], last[2] + 1):
                grid[i, j, m] = wp.uint8(1)


def splat_occupancy(
    cells_lo: torch.Tensor,
    cell_size: torch.Tensor,
    nearest_ip: torch.Tensor,
    ip_rest: torch.Tensor,
    ip_displacement: torch.Tensor,
    F: torch.Tensor,
    grad_F: torch.Tensor,
    aabb: torch.Tensor,
    shape: tuple[int, int, int],
) -> torch.Tensor:
    """Forward-warp occupied rest cells into a deformed-space grid (Eq. 19 in the explicit direction).

    Each cell's corners x map to x + u_k + (F_k − I) d + ½ ∇F_k : d d, d = x − x_k, about the cell's nearest rest
    IP k; every deformed cell the mapped corners' bounding box overlaps (shrunk by 1e-4 of a cell, so a cell mapped
    onto itself marks only itself) is marked, at most 3 per axis per cell. One Warp thread per rest cell, in float64
    (so with zero displacement every corner maps to itself bit for bit). A renderer's frame calls it once; as a kernel
    rather than ~40 torch operations it spares a frame bound by its host (``docs/benchmarks.md``).

    Args:
        cells_lo: float64 ``[C, 3]`` lower corners of the occupied rest cells, metres.
        cell_size: float64 ``[3]`` rest cell edges, metres (read on the host: pass it there to spare a transfer).
        nearest_ip: int64 ``[C]`` nearest rest IP of each cell.
        ip_rest, ip_displacement: float64 ``[K, 3]`` x_k and u(x_k), metres.
        F, grad_F: float64 ``[K, 3, 3]`` and ``[K, 3, 3, 3]`` at the IPs.
        aabb: ``[2, 3]`` box of the deformed grid, metres (read on the host, like ``cell_size``).
        shape: cells of the deformed grid per axis.

    Returns:
        bool ``[Gx, Gy, Gz]``.
    """
    device = cells_lo.device
    f64 = dict(dtype=torch.float64, device=device)
    grid = torch.zeros(shape, dtype=torch.uint8, device=device)
    if cells_lo.shape[0] == 0:
        return grid.view(torch.bool)
    box = aabb.detach().to(dtype=torch.float64).cpu()
    deformed_cell = (box[1] - box[0]) / torch.tensor(shape, dtype=torch.float64)
    wp.launch(
        _splat_occupancy_wp,
        dim=cells_lo.shape[0],
        inputs=[
            backend.warp_arg(cells_lo.to(**f64).contiguous(), dtype=wp.vec3d),
            wp.vec3d(*cell_size.detach().to(torch.float64).cpu().tolist()),
            backend.warp_arg(nearest_ip.to(device=device, dtype=torch.int64).contiguous()),
            backend.warp_arg(ip_rest.to(**f64).contiguous(), dtype=wp.vec3d),
            backend.warp_arg(ip_displacement.to(**f64).contiguous(), dtype=wp.vec3d),
            backend.warp_arg(F.to(**f64).contiguous(), dtype=wp.mat33d),
            backend.warp_arg(grad_F.to(**f64).contiguous()),
            wp.vec3d(*box[0].tolist()),
            wp.vec3d(*deformed_cell.tolist()),
            backend.warp_arg(grid),
        ],
        device=backend.warp_device(),
    )
    return grid.view(torch.bool)  # no copy: the kernel writes only 0 and 1, which is how bool is stored


def _check_warp_arguments(samples, neighbours, distances, ip_deformed, ip_displacement, F, grad_F, cutoff):
    count = samples.shape[0] if isinstance(samples, torch.Tensor) and samples.dim() == 2 else -1
    width = neighbours.shape[1] if isinstance(neighbours, torch.Tensor) and neighbours.dim() == 2 else -1
    _check_tensors(
        (
            ("samples", samples, torch.float32, (count, 3)),
            ("neighbours", neighbours, torch.int32, (count, width)),
            ("distances", distances, torch.float32, (count, width)),
        )
    )
    _check_ips(ip_deformed, ip_displacement, F, grad_F, cutoff)
    return count, width


def _check_ips(ip_deformed, ip_displacement, F, grad_F, cutoff) -> None:
    ips = ip_deformed.shape[0] if isinstance(ip_deformed, torch.Tensor) and ip_deformed.dim() == 2 else -1
    _check_tensors(
        (
            ("ip_deformed", ip_deformed, torch.float32, (ips, 3)),
            ("ip_displacement", ip_displacement, torch.float32, (ips, 3)),
            ("F", F, torch.float32, (ips, 3, 3)),
            ("grad_F", grad_F, torch.float32, (ips, 3, 3, 3)),
            ("cutoff", cutoff, torch.float32, (ips,)),
        )
    )


def _check_tensors(expected) -> None:
    for name, tensor, dtype, shape in expected:
        if not isinstance(tensor, torch.Tensor) or tensor.dtype != dtype:
            raise TypeError(f"{name} must be a {dtype} tensor {list(shape)}; convert it with .to({dtype})")
        if tuple(tensor.shape) != shape or min(shape) < 0:
            raise ValueError(
                f"{name} must have shape {list(shape)} (S samples, N neighbours, K IPs), got {list(tensor.shape)}"
            )
