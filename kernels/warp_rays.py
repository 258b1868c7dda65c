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
``python -m apps.bench --workload warp_rays --size paper`` (1M samples, 3 IPs each, random F and ∇F, 3.7
iterations on average) on this project's shared 2-core CPU, under load from other jobs: 168 ms (6.2 Msamples/s)
against 27.1 s for the torch reference (:mod:`kernels.reference.warp_rays`, batched ``linalg.solve``), 161x.
Not yet measured on CUDA.
"""

from typing import NamedTuple

import taichi as ti
import torch

from kernels import backend

__all__ = ["SINGULAR_DETERMINANT", "WarpedSamples", "warp_to_rest"]

SINGULAR_DETERMINANT = 1e-6
"""``|det J|`` below which a Newton Jacobian (dimensionless) counts as singular."""

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


def _check_warp_arguments(samples, neighbours, distances, ip_deformed, ip_displacement, F, grad_F, cutoff):
    count = samples.shape[0] if isinstance(samples, torch.Tensor) and samples.dim() == 2 else -1
    ips = ip_deformed.shape[0] if isinstance(ip_deformed, torch.Tensor) and ip_deformed.dim() == 2 else -1
    width = neighbours.shape[1] if isinstance(neighbours, torch.Tensor) and neighbours.dim() == 2 else -1
    expected = (
        ("samples", samples, torch.float32, (count, 3)),
        ("neighbours", neighbours, torch.int32, (count, width)),
        ("distances", distances, torch.float32, (count, width)),
        ("ip_deformed", ip_deformed, torch.float32, (ips, 3)),
        ("ip_displacement", ip_displacement, torch.float32, (ips, 3)),
        ("F", F, torch.float32, (ips, 3, 3)),
        ("grad_F", grad_F, torch.float32, (ips, 3, 3, 3)),
        ("cutoff", cutoff, torch.float32, (ips,)),
    )
    for name, tensor, dtype, shape in expected:
        if not isinstance(tensor, torch.Tensor) or tensor.dtype != dtype:
            raise TypeError(f"{name} must be a {dtype} tensor {list(shape)}; convert it with .to({dtype})")
        if tuple(tensor.shape) != shape or min(shape) < 0:
            raise ValueError(
                f"{name} must have shape {list(shape)} (S samples, N neighbours, K IPs), got {list(tensor.shape)}"
            )
    return count, width
