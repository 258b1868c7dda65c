"""NeRF volume rendering (PIE-NeRF §3.1, instant-NGP): ray marching through an occupancy grid and compositing.

A pixel's colour is the emission-absorption integral along its ray, evaluated on samples ``i`` at depths
``t_i`` with spacing ``δ_i`` (Max 1995; Mildenhall et al. 2020, Eq. 3):

    α_i = 1 − exp(−σ_i δ_i),   T_i = Π_{j<i} (1 − α_j),   w_i = T_i α_i,
    C = Σ_i w_i c_i,   A = Σ_i w_i (opacity),   D = Σ_i w_i t_i (expected depth).

Samples are *packed*: the samples of ray ``r`` are rows ``ray_offsets[r] : ray_offsets[r + 1]`` of every
per-sample tensor (CSR layout), so rays with few samples cost little and empty rays cost nothing.

Ray marching (:func:`march_rays`) follows instant-NGP (Müller et al. 2022, Appendix E.1):

* a ray is clipped to the scene box and to ``[near, far]``; sample ``i`` sits at ``t_i`` and represents
  ``[t_i, t_i + δ_i)``;
* the step grows with distance, ``δ(t) = clamp(t · cone_angle, min_step, max_step)``: with
  ``cone_angle = 0`` (synthetic, object-centred scenes) it is the constant ``min_step``; with
  ``cone_angle ≈ 1/256`` the step keeps a constant angular footprint far from the camera;
* a sample whose occupancy-grid cell is empty is not emitted; the march jumps whole steps past the cell's
  exit, so the samples that are emitted stay on the ray's lattice ``t_0 + k δ`` (constant step);
* at most ``max_samples`` samples per ray are emitted.

Compositing stops early once transmittance falls below ``transmittance_threshold`` (1e-4, as instant-NGP):
sample ``i`` is composited only while ``T_i ≥ 1e-4``, so the samples after it carry weight 0 and receive
zero gradient. The backward pass (:func:`composite_backward`) is the reverse-mode derivative of exactly
that truncated sum (the stopping index held fixed), computed as instant-NGP does from the forward outputs
in a second front-to-back sweep, with no per-sample storage beyond the inputs:

    ∂C/∂c_i = w_i,    ∂C/∂σ_i = δ_i (T_{i+1} c_i − (C − C_{≤i})),
    ∂A/∂σ_i = δ_i (T_{i+1} − (A − A_{≤i})),    ∂D/∂σ_i = δ_i (T_{i+1} t_i − (D − D_{≤i})),

where ``C_{≤i}`` is the running sum up to and including sample ``i``.

Rendering in rounds (instant-NGP's inference loop): :func:`march_start` clips every ray to the box, and each
call of :func:`march_resume` marches the rays still alive by at most ``k`` more samples, from the depth where
their previous round stopped (:class:`MarchState`), skipping rays whose transmittance already fell below the
threshold; :func:`composite_accumulate` composites a round's samples onto each ray's running sums
(:class:`CompositeState`). The march loop and the compositing loop are the very Taichi functions the one-pass
kernels run, so the rounds of a ray emit bit for bit the samples of one :func:`march_rays` call and composite to
the sums of one :func:`composite_forward` call; what changes is that samples behind an opaque surface are never
marched, and so never shaded.

Framework: Taichi. The kernels loop over one ray per thread with a data-dependent inner loop, the shape
the project's rule gives to Taichi for per-sample rendering that must run interactively on a CPU (Taichi
runs them on every core; Warp's CPU backend on one). The two kernels a renderer launches every round,
:func:`march_resume` and :func:`composite_accumulate`, are kept in Warp as well (``framework=``), with the same
loops, and Warp is their default on CUDA: a frame launches them a dozen times, and a Taichi launch costs the host
several times what a Warp launch does (:func:`kernels.backend.default_framework`). On the CPU the Warp march is
bit for bit Taichi's; on CUDA the two compilers may fuse multiply-adds differently, so a sample can move in the
last bit. Timings against the torch reference: ``docs/benchmarks.md``.
"""

# Warp needs int(0)/float(0.0) to declare variables that change inside dynamic loops.
# ruff: noqa: UP018

import functools
import math
from typing import NamedTuple

import taichi as ti
import torch
import warp as wp

from kernels import backend

wp.set_module_options({"enable_backward": False})  # rendering kernels: forward only, no adjoints to compile

__all__ = [
    "DEFAULT_TRANSMITTANCE_THRESHOLD",
    "CompositeState",
    "MarchState",
    "RaySamples",
    "RoundSamples",
    "VolumeRenderFunction",
    "composite",
    "composite_accumulate",
    "composite_backward",
    "composite_forward",
    "composite_start",
    "gather_ray_rows",
    "march_rays",
    "march_resume",
    "march_start",
]

DEFAULT_TRANSMITTANCE_THRESHOLD = 1e-4
"""Compositing stops once ``T_i`` drops below this (instant-NGP's early ray termination)."""

_TINY_DIRECTION = 1e-12  # direction components smaller than this are replaced by ±1e-12 (no 0 divisions)


# ---------------------------------------------------------------------------------------------------
# Ray marching
# ---------------------------------------------------------------------------------------------------


@ti.func
def _safe_component_ti(value):
    result = value
    if ti.abs(value) < _TINY_DIRECTION:
        result = _TINY_DIRECTION if value >= 0.0 else -_TINY_DIRECTION
    return result


@ti.func
def _ray_box_ti(o, d, lo, hi):
    """Slab test: entry and exit depths of the ray ``o + t d`` through the box ``[lo, hi]``."""
    t_enter, t_exit = -math.inf, math.inf
    for a in ti.static(range(3)):
        inv = 1.0 / _safe_component_ti(d[a])
        t0, t1 = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
        t_enter = ti.max(t_enter, ti.min(t0, t1))
        t_exit = ti.min(t_exit, ti.max(t0, t1))
    return t_enter, t_exit


@ti.func
def _step_ti(t, min_step, max_step, cone_angle):
    """Step size ``δ(t) = clamp(t · cone_angle, min_step, max_step)``, metres."""
    return ti.math.clamp(t * cone_angle, min_step, max_step)


@ti.func
def _cell_exit_ti(p, d, cell, lo, cell_size):
    """Distance along ``d`` from ``p`` to the boundary of grid cell ``cell`` (≥ 0)."""
    t_exit = math.inf
    for a in ti.static(range(3)):
        da = _safe_component_ti(d[a])
        face = lo[a] + ti.cast(cell[a] + (1 if da > 0.0 else 0), ti.f32) * cell_size[a]
        t_exit = ti.min(t_exit, (face - p[a]) / da)
    return ti.max(t_exit, 0.0)


@ti.func
def _march_segment_ti(
    o,
    d,
    t,
    t_end,
    budget,
    occupancy: ti.template(),
    lo,
    cell_size,
    resolution,
    min_step,
    max_step,
    cone_angle,
    positions: ti.template(),
    depths: ti.template(),
    deltas: ti.template(),
    base,
    write: ti.template(),
):
    """March one ray from depth ``t`` until ``budget`` samples are emitted or ``t`` reaches ``t_end``.

    Samples go to rows ``base, base + 1, …`` (when ``write``). Returns ``(t, emitted)``: the depth to resume from,
    on the same lattice, and the number of samples emitted. :func:`march_rays` runs it once per ray,
    :func:`march_resume` in rounds; both therefore emit the same samples.
    """
    emitted = 0
    while t < t_end and emitted < budget:
        dt = _step_ti(t, min_step, max_step, cone_angle)
        p = o + t * d
        cell = ti.math.clamp(ti.cast(ti.floor((p - lo) / cell_size), ti.i32), 0, resolution - 1)
        if occupancy[cell[0], cell[1], cell[2]] != 0:
            if ti.static(write):
                positions[base + emitted] = p
                depths[base + emitted] = t
                deltas[base + emitted] = dt
            emitted += 1
            t += dt
        else:
            # Jump whole steps to just past the cell's exit, staying on the lattice t_0 + k dt.
            skip = _cell_exit_ti(p, d, cell, lo, cell_size)
            t += (ti.floor(skip / dt) + 1.0) * dt
    return t, emitted


@ti.kernel
def _march_ti(
    origins: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    directions: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    near: ti.types.ndarray(dtype=ti.f32, ndim=1),
    far: ti.types.ndarray(dtype=ti.f32, ndim=1),
    jitter: ti.types.ndarray(dtype=ti.f32, ndim=1),
    occupancy: ti.types.ndarray(dtype=ti.u8, ndim=3),
    lo: ti.math.vec3,
    hi: ti.math.vec3,
    min_step: ti.f32,
    max_step: ti.f32,
    cone_angle: ti.f32,
    max_samples: ti.i32,
    ray_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    positions: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    depths: ti.types.ndarray(dtype=ti.f32, ndim=1),
    deltas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    write: ti.template(),
):
    """Count (``write=False``: into ``ray_offsets[r + 1]``) or emit (``write=True``) each ray's samples."""
    resolution = ti.Vector([occupancy.shape[0], occupancy.shape[1], occupancy.shape[2]])
    cell_size = (hi - lo) / ti.cast(resolution, ti.f32)
    for r in range(origins.shape[0]):
        o, d = origins[r], directions[r]
        t_enter, t_exit = _ray_box_ti(o, d, lo, hi)
        t_begin, t_end = ti.max(t_enter, near[r]), ti.min(t_exit, far[r])
        count = 0
        base = 0
        if ti.static(write):
            base = ray_offsets[r]
        if t_begin < t_end:
            t = t_begin + jitter[r] * _step_ti(t_begin, min_step, max_step, cone_angle)
            _, emitted = _march_segment_ti(
                o,
                d,
                t,
                t_end,
                max_samples,
                occupancy,
                lo,
                cell_size,
                resolution,
                min_step,
                max_step,
                cone_angle,
                positions,
                depths,
                deltas,
                base,
                write,
            )
            count = emitted
        if ti.static(not write):
            ray_offsets[r + 1] = count


class RaySamples(NamedTuple):
    """Packed samples of a batch of rays (CSR layout: ray ``r`` owns rows ``ray_offsets[r]:ray_offsets[r+1]``).

    Attributes:
        positions: float32 ``[S, 3]`` sample positions ``o + t d``, metres.
        depths: float32 ``[S]`` ``t_i``, metres along the (unit) direction.
        deltas: float32 ``[S]`` ``δ_i``, metres.
        ray_offsets: int32 ``[R + 1]`` start row of every ray, ``ray_offsets[R] = S``.
        ray_indices: int64 ``[S]`` the ray of every sample.
    """

    positions: torch.Tensor
    depths: torch.Tensor
    deltas: torch.Tensor
    ray_offsets: torch.Tensor
    ray_indices: torch.Tensor

    @property
    def counts(self) -> torch.Tensor:
        """int32 ``[R]`` samples per ray."""
        return self.ray_offsets[1:] - self.ray_offsets[:-1]


def march_rays(
    origins: torch.Tensor,
    directions: torch.Tensor,
    near: torch.Tensor | float,
    far: torch.Tensor | float,
    occupancy: torch.Tensor,
    aabb: torch.Tensor,
    min_step: float,
    *,
    max_step: float | None = None,
    cone_angle: float = 0.0,
    max_samples: int = 1024,
    jitter: torch.Tensor | None = None,
) -> RaySamples:
    """Sample rays through the scene box, skipping cells the occupancy grid marks empty (instant-NGP §E.1).

    Args:
        origins: float32 ``[R, 3]`` ray origins, metres, on the backend device.
        directions: float32 ``[R, 3]`` unit directions (``t`` is then a distance in metres).
        near, far: ``[R]`` or scalars: the depth interval to sample, metres (clipped to the box).
        occupancy: ``[Gx, Gy, Gz]`` bool or uint8 grid over ``aabb`` (cell ``[i, j, k]`` spans
            ``lo + (i, j, k) · (hi − lo) / G``), non-zero where the scene may hold density.
        aabb: ``[2, 3]`` scene box ``(lo, hi)``, metres.
        min_step: smallest (and, with ``cone_angle = 0``, every) step ``δ``, metres.
        max_step: largest step, metres (default: ``min_step`` when ``cone_angle = 0``, else unbounded).
        cone_angle: growth of the step with depth, ``δ(t) = clamp(t · cone_angle, min_step, max_step)``.
        max_samples: most samples emitted per ray.
        jitter: float32 ``[R]`` in ``[0, 1)``: the first sample sits ``jitter · δ`` past the ray's entry
            (random during training, so the lattice does not alias); ``None``: no offset.

    Returns:
        :class:`RaySamples`.
    """
    rays = _check_rays(origins, directions)
    device = origins.device
    near_t, far_t = (_per_ray(v, rays, name, device) for v, name in ((near, "near"), (far, "far")))
    jitter_t = torch.zeros(rays, device=device) if jitter is None else _per_ray(jitter, rays, "jitter", device)
    grid = _check_occupancy(occupancy)
    lo, hi = _box(aabb)
    steps = _steps(min_step, max_step, cone_angle, max_samples)

    ray_offsets = torch.zeros(rays + 1, dtype=torch.int32, device=device)
    empty_vec, empty = torch.empty(0, 3, device=device), torch.empty(0, device=device)
    args = [backend.taichi_arg(t.detach().contiguous()) for t in (origins, directions, near_t, far_t, jitter_t, grid)]
    if rays > 0:
        _march_ti(*args, lo, hi, *steps, backend.taichi_arg(ray_offsets), empty_vec, empty, empty, False)
    ray_offsets = torch.cumsum(ray_offsets, 0, dtype=torch.int32)
    samples = int(ray_offsets[-1])
    positions = torch.empty(samples, 3, device=device)
    depths, deltas = torch.empty(samples, device=device), torch.empty(samples, device=device)
    if samples > 0:
        outputs = (backend.taichi_arg(t) for t in (ray_offsets, positions, depths, deltas))
        _march_ti(*args, lo, hi, *steps, *outputs, True)
    ray_indices = torch.repeat_interleave(
        torch.arange(rays, device=device), (ray_offsets[1:] - ray_offsets[:-1]).long(), output_size=samples
    )
    return RaySamples(positions, depths, deltas, ray_offsets, ray_indices)


# Marching in rounds: each ray's march is resumed where the previous round left it.


@ti.kernel
def _march_start_ti(
    origins: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    directions: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    near: ti.types.ndarray(dtype=ti.f32, ndim=1),
    far: ti.types.ndarray(dtype=ti.f32, ndim=1),
    lo: ti.math.vec3,
    hi: ti.math.vec3,
    t: ti.types.ndarray(dtype=ti.f32, ndim=1),
    t_end: ti.types.ndarray(dtype=ti.f32, ndim=1),
    count: ti.types.ndarray(dtype=ti.i32, ndim=1),
):
    for r in range(origins.shape[0]):
        t_enter, t_exit = _ray_box_ti(origins[r], directions[r], lo, hi)
        t[r] = ti.max(t_enter, near[r])
        t_end[r] = ti.min(t_exit, far[r])
        count[r] = 0


@ti.kernel
def _march_resume_ti(
    origins: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    directions: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    rays: ti.types.ndarray(dtype=ti.i64, ndim=1),
    t: ti.types.ndarray(dtype=ti.f32, ndim=1),
    t_end: ti.types.ndarray(dtype=ti.f32, ndim=1),
    count: ti.types.ndarray(dtype=ti.i32, ndim=1),
    transmittance: ti.types.ndarray(dtype=ti.f32, ndim=1),
    threshold: ti.f32,
    occupancy: ti.types.ndarray(dtype=ti.u8, ndim=3),
    lo: ti.math.vec3,
    hi: ti.math.vec3,
    min_step: ti.f32,
    max_step: ti.f32,
    cone_angle: ti.f32,
    max_samples: ti.i32,
    per_ray: ti.i32,
    positions: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    depths: ti.types.ndarray(dtype=ti.f32, ndim=1),
    deltas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    emitted: ti.types.ndarray(dtype=ti.i32, ndim=1),
):
    resolution = ti.Vector([occupancy.shape[0], occupancy.shape[1], occupancy.shape[2]])
    cell_size = (hi - lo) / ti.cast(resolution, ti.f32)
    for i in range(rays.shape[0]):
        r = rays[i]
        n = 0
        if transmittance[r] >= threshold:
            budget = ti.min(per_ray, max_samples - count[r])
            t_next, got = _march_segment_ti(
                origins[r],
                directions[r],
                t[r],
                t_end[r],
                budget,
                occupancy,
                lo,
                cell_size,
                resolution,
                min_step,
                max_step,
                cone_angle,
                positions,
                depths,
                deltas,
                i * per_ray,
                True,
            )
            t[r] = t_next
            count[r] += got
            n = got
        emitted[i] = n


# The same march in Warp (``framework="warp"``, the default on CUDA): rounds issue a launch per round, and a Warp
# launch costs the host far less than a Taichi one (:func:`kernels.backend.default_framework`).

_TINY_DIRECTION_WP = wp.constant(_TINY_DIRECTION)


@wp.func
def _safe_component_wp(value: float):
    result = value
    if wp.abs(value) < _TINY_DIRECTION_WP:
        result = wp.where(value >= 0.0, _TINY_DIRECTION_WP, -_TINY_DIRECTION_WP)
    return result


@wp.func
def _cell_exit_wp(p: wp.vec3, d: wp.vec3, cell: wp.vec3i, lo: wp.vec3, cell_size: wp.vec3):
    t_exit = wp.inf
    for a in range(3):
        da = _safe_component_wp(d[a])
        face = lo[a] + float(cell[a] + wp.where(da > 0.0, 1, 0)) * cell_size[a]
        t_exit = wp.min(t_exit, (face - p[a]) / da)
    return wp.max(t_exit, 0.0)


@wp.kernel
def _march_resume_wp(
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    rays: wp.array(dtype=wp.int64),
    t: wp.array(dtype=wp.float32),
    t_end: wp.array(dtype=wp.float32),
    count: wp.array(dtype=wp.int32),
    transmittance: wp.array(dtype=wp.float32),
    threshold: float,
    occupancy: wp.array3d(dtype=wp.uint8),
    lo: wp.vec3,
    hi: wp.vec3,
    min_step: float,
    max_step: float,
    cone_angle: float,
    max_samples: int,
    per_ray: int,
    positions: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=wp.float32),
    deltas: wp.array(dtype=wp.float32),
    emitted: wp.array(dtype=wp.int32),
):
    """:func:`_march_resume_ti` with :func:`_march_segment_ti`'s loop inlined (same arithmetic, same lattice)."""
    i = wp.tid()
    r = int(rays[i])
    resolution = wp.vec3i(occupancy.shape[0], occupancy.shape[1], occupancy.shape[2])
    cell_size = wp.cw_div(hi - lo, wp.vec3(float(resolution[0]), float(resolution[1]), float(resolution[2])))
    n = int(0)
    if transmittance[r] >= threshold:
        budget = wp.min(per_ray, max_samples - count[r])
        o = origins[r]
        d = directions[r]
        depth = float(t[r])
        end = t_end[r]
        base = i * per_ray
        while depth < end and n < budget:
            dt = wp.clamp(depth * cone_angle, min_step, max_step)
            p = o + depth * d
            u = wp.cw_div(p - lo, cell_size)
            cell = wp.vec3i(
                wp.clamp(int(wp.floor(u[0])), 0, resolution[0] - 1),
                wp.clamp(int(wp.floor(u[1])), 0, resolution[1] - 1),
                wp.clamp(int(wp.floor(u[2])), 0, resolution[2] - 1),
            )
            if occupancy[cell[0], cell[1], cell[2]] != wp.uint8(0):
                positions[base + n] = p
                depths[base + n] = depth
                deltas[base + n] = dt
                n += 1
                depth += dt
            else:
                skip = _cell_exit_wp(p, d, cell, lo, cell_size)
                depth += (wp.floor(skip / dt) + 1.0) * dt
        t[r] = depth
        count[r] = count[r] + n
    emitted[i] = n


class MarchState(NamedTuple):
    """Where each ray's march stands between rounds (:func:`march_start`, :func:`march_resume`).

    Attributes:
        t: float32 ``[R]`` depth of the next candidate sample, metres (on the ray's step lattice).
        t_end: float32 ``[R]`` depth where the march ends: the box's exit or ``far``, whichever is nearer.
        count: int32 ``[R]`` samples emitted so far (at most ``max_samples``).
    """

    t: torch.Tensor
    t_end: torch.Tensor
    count: torch.Tensor


class RoundSamples(NamedTuple):
    """The samples of one round of :func:`march_resume`, ``k`` slots per marched ray.

    Ray ``i`` of the round filled slots ``[i, :counts[i]]``; the other slots hold zeros.

    Attributes:
        positions: float32 ``[A, k, 3]`` sample positions, metres.
        depths: float32 ``[A, k]`` ``t_i``, metres.
        deltas: float32 ``[A, k]`` ``δ_i``, metres.
        counts: int32 ``[A]`` samples emitted by each ray; fewer than ``k`` means its march is over (or its
            transmittance was below the threshold: then 0).
    """

    positions: torch.Tensor
    depths: torch.Tensor
    deltas: torch.Tensor
    counts: torch.Tensor


def march_start(
    origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor | float, far: torch.Tensor | float, aabb
) -> MarchState:
    """The state before the first round of a march resumed in rounds (:func:`march_resume`).

    Args:
        origins, directions: float32 ``[R, 3]`` rays (unit directions), metres, on the backend device.
        near, far: ``[R]`` or scalars: the depth interval to sample, metres (clipped to ``aabb``).
        aabb: ``[2, 3]`` scene box ``(lo, hi)``, metres.

    Returns:
        :class:`MarchState` with ``t`` at each ray's entry (no jitter: rendering, not training).
    """
    rays = _check_rays(origins, directions)
    device = origins.device
    near_t, far_t = (_per_ray(v, rays, name, device) for v, name in ((near, "near"), (far, "far")))
    lo, hi = _box(aabb)
    state = MarchState(
        torch.empty(rays, device=device),
        torch.empty(rays, device=device),
        torch.empty(rays, dtype=torch.int32, device=device),
    )
    if rays > 0:
        inputs = (origins.detach().contiguous(), directions.detach().contiguous(), near_t, far_t)
        _march_start_ti(*(backend.taichi_arg(v) for v in inputs), lo, hi, *(backend.taichi_arg(v) for v in state))
    return state


def march_resume(
    state: MarchState,
    origins: torch.Tensor,
    directions: torch.Tensor,
    rays: torch.Tensor,
    occupancy: torch.Tensor,
    aabb,
    min_step: float,
    *,
    samples_per_ray: int,
    max_step: float | None = None,
    cone_angle: float = 0.0,
    max_samples: int = 1024,
    transmittance: torch.Tensor | None = None,
    transmittance_threshold: float = 0.0,
    framework: str | None = None,
) -> RoundSamples:
    """One round of a resumable march: rays ``rays`` go on from ``state`` until each has emitted
    ``samples_per_ray`` more samples (or its march ended); ``state`` is updated in place.

    Every round continues the very loop of :func:`march_rays` from the stored depth, so the rounds of a ray,
    concatenated, are exactly the samples one :func:`march_rays` call emits (same lattice, same cone steps, same
    ``max_samples`` cap), bit for bit. Rendering marches a few samples per round, shades and composites them, and
    stops rays once opaque (instant-NGP's inference loop), instead of marching every sample up front.

    Args:
        state: from :func:`march_start` over the same ``origins`` and ``directions`` (float32 ``[R, 3]``).
        rays: int64 ``[A]`` the rays to march this round (distinct indices into ``origins``).
        occupancy, aabb, min_step, max_step, cone_angle, max_samples: as :func:`march_rays`; ``occupancy``
            uint8 avoids a conversion per round.
        samples_per_ray: ``k``, the most samples a ray emits this round.
        transmittance: float32 ``[R]``, or ``None``: rays whose transmittance is below ``transmittance_threshold``
            emit nothing (early ray termination, as :func:`composite_forward` stops compositing there).
        framework: ``"taichi"`` or ``"warp"`` (the same loop; the Warp launch costs the host less);
            ``None``: :func:`kernels.backend.default_framework`.

    Returns:
        :class:`RoundSamples` with ``k`` slots per ray of ``rays``.
    """
    count = _check_rays(origins, directions)
    device = origins.device
    framework = backend.check_framework(framework)
    if samples_per_ray < 1:
        raise ValueError(f"samples_per_ray must be at least 1, got {samples_per_ray}")
    if not (isinstance(rays, torch.Tensor) and rays.dtype == torch.int64 and rays.dim() == 1):
        raise TypeError("rays must be an int64 tensor [A] of ray indices; convert it with .long()")
    for name, tensor, dtype in (
        ("t", state.t, torch.float32),
        ("t_end", state.t_end, torch.float32),
        ("count", state.count, torch.int32),
    ):
        if tensor.dtype != dtype or tensor.shape != (count,):
            raise ValueError(
                f"state.{name} must be {dtype} [R] = [{count}] (from march_start over these rays), "
                f"got {tensor.dtype} {list(tensor.shape)}"
            )
    if transmittance is None:
        transmittance, transmittance_threshold = torch.ones(count, device=device), 0.0
    elif transmittance.dtype != torch.float32 or transmittance.shape != (count,):
        raise ValueError(
            f"transmittance must be float32 [R] = [{count}], got {transmittance.dtype} {list(transmittance.shape)}"
        )
    grid = _check_occupancy(occupancy)
    lo, hi = _box(aabb, framework)
    steps = _steps(min_step, max_step, cone_angle, max_samples)
    marched, k = rays.shape[0], int(samples_per_ray)
    positions = torch.zeros(marched, k, 3, device=device)
    depths, deltas = torch.zeros(marched, k, device=device), torch.zeros(marched, k, device=device)
    emitted = torch.zeros(marched, dtype=torch.int32, device=device)
    if marched > 0:
        inputs = (
            origins.detach().contiguous(),
            directions.detach().contiguous(),
            rays.contiguous(),
            *state,
            transmittance.contiguous(),
        )
        outputs = (positions.view(-1, 3), depths.view(-1), deltas.view(-1), emitted)
        if framework == "warp":
            wp.launch(
                _march_resume_wp,
                dim=marched,
                inputs=[
                    *_warp_views(inputs),
                    float(transmittance_threshold),
                    backend.warp_arg(grid),
                    lo,
                    hi,
                    *steps,
                    k,
                    *_warp_views(outputs),
                ],
                device=backend.warp_device(),
            )
            return RoundSamples(positions, depths, deltas, emitted)
        _march_resume_ti(
            *(backend.taichi_arg(v) for v in inputs),
            float(transmittance_threshold),
            backend.taichi_arg(grid),
            lo,
            hi,
            *steps,
            k,
            *(backend.taichi_arg(v) for v in outputs),
        )
    return RoundSamples(positions, depths, deltas, emitted)


# ---------------------------------------------------------------------------------------------------
# Compositing
# ---------------------------------------------------------------------------------------------------


@ti.func
def _composite_ray_ti(
    sigmas: ti.template(),
    colors: ti.template(),
    deltas: ti.template(),
    depths: ti.template(),
    start,
    end,
    threshold,
    transmittance,
    color,
    opacity,
    depth,
    weights: ti.template(),
    write_weights: ti.template(),
):
    """Composite samples ``start:end`` of one ray onto its running sums, front to back, stopping once the
    transmittance is below ``threshold``; returns ``(transmittance, color, opacity, depth, samples used)``.
    :func:`composite_forward` starts it from ``(1, 0, 0, 0)``, :func:`composite_accumulate` from the sums of
    earlier rounds, so compositing a ray in rounds runs the same arithmetic as compositing it at once."""
    used = 0
    for i in range(start, end):
        if transmittance < threshold:
            break
        alpha = 1.0 - ti.exp(-sigmas[i] * deltas[i])
        weight = transmittance * alpha
        color += weight * colors[i]
        opacity += weight
        depth += weight * depths[i]
        if ti.static(write_weights):
            weights[i] = weight
        transmittance *= 1.0 - alpha
        used += 1
    return transmittance, color, opacity, depth, used


@ti.kernel
def _composite_forward_ti(
    sigmas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    deltas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    depths: ti.types.ndarray(dtype=ti.f32, ndim=1),
    ray_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    threshold: ti.f32,
    out_color: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    out_opacity: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out_depth: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out_used: ti.types.ndarray(dtype=ti.i32, ndim=1),
    weights: ti.types.ndarray(dtype=ti.f32, ndim=1),
    write_weights: ti.template(),
):
    for r in range(ray_offsets.shape[0] - 1):
        _, color, opacity, depth, used = _composite_ray_ti(
            sigmas,
            colors,
            deltas,
            depths,
            ray_offsets[r],
            ray_offsets[r + 1],
            threshold,
            1.0,
            ti.math.vec3(0.0),
            0.0,
            0.0,
            weights,
            write_weights,
        )
        out_color[r] = color
        out_opacity[r] = opacity
        out_depth[r] = depth
        out_used[r] = used


def composite_forward(
    sigmas: torch.Tensor,
    colors: torch.Tensor,
    deltas: torch.Tensor,
    depths: torch.Tensor,
    ray_offsets: torch.Tensor,
    *,
    transmittance_threshold: float = DEFAULT_TRANSMITTANCE_THRESHOLD,
    return_weights: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Composite packed samples into per-ray colour, opacity and depth (module docstring, NeRF Eq. 3).

    Args:
        sigmas: float32 ``[S]`` densities σ_i ≥ 0, per metre.
        colors: float32 ``[S, 3]`` emitted colours c_i.
        deltas: float32 ``[S]`` step lengths δ_i, metres.
        depths: float32 ``[S]`` sample depths t_i, metres.
        ray_offsets: int32 ``[R + 1]`` CSR offsets of the rays' samples.
        transmittance_threshold: a ray stops at the first sample with ``T_i`` below this.
        return_weights: also return the weights ``w_i`` ``[S]`` (0 after termination).

    Returns:
        ``(color [R, 3], opacity [R], depth [R], used [R] int32, weights [S] or None)``; ``used`` counts the
        samples composited before termination, ``depth`` is ``Σ w_i t_i`` (not divided by the opacity).
    """
    rays = _check_samples(sigmas, colors, deltas, depths, ray_offsets)
    device = sigmas.device
    color = torch.empty(rays, 3, device=device)
    opacity, depth = torch.empty(rays, device=device), torch.empty(rays, device=device)
    used = torch.empty(rays, dtype=torch.int32, device=device)
    weights = torch.zeros(sigmas.shape[0] if return_weights else 0, device=device)
    if rays > 0:
        _composite_forward_ti(
            *(backend.taichi_arg(t.detach().contiguous()) for t in (sigmas, colors, deltas, depths, ray_offsets)),
            float(transmittance_threshold),
            *(backend.taichi_arg(t) for t in (color, opacity, depth, used, weights)),
            return_weights,
        )
    return color, opacity, depth, used, (weights if return_weights else None)


@ti.kernel
def _composite_accumulate_ti(
    sigmas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    deltas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    depths: ti.types.ndarray(dtype=ti.f32, ndim=1),
    ray_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    rays: ti.types.ndarray(dtype=ti.i64, ndim=1),
    threshold: ti.f32,
    color: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    opacity: ti.types.ndarray(dtype=ti.f32, ndim=1),
    depth: ti.types.ndarray(dtype=ti.f32, ndim=1),
    transmittance: ti.types.ndarray(dtype=ti.f32, ndim=1),
    no_weights: ti.types.ndarray(dtype=ti.f32, ndim=1),
):
    for i in range(rays.shape[0]):
        r = rays[i]
        t_r, c_r, o_r, d_r, _ = _composite_ray_ti(
            sigmas,
            colors,
            deltas,
            depths,
            ray_offsets[i],
            ray_offsets[i + 1],
            threshold,
            transmittance[r],
            color[r],
            opacity[r],
            depth[r],
            no_weights,
            False,
        )
        transmittance[r] = t_r
        color[r] = c_r
        opacity[r] = o_r
        depth[r] = d_r


@wp.kernel
def _composite_accumulate_wp(
    sigmas: wp.array(dtype=wp.float32),
    colors: wp.array(dtype=wp.vec3),
    deltas: wp.array(dtype=wp.float32),
    depths: wp.array(dtype=wp.float32),
    ray_offsets: wp.array(dtype=wp.int32),
    rays: wp.array(dtype=wp.int64),
    threshold: float,
    color: wp.array(dtype=wp.vec3),
    opacity: wp.array(dtype=wp.float32),
    depth: wp.array(dtype=wp.float32),
    transmittance: wp.array(dtype=wp.float32),
):
    """:func:`_composite_accumulate_ti` with :func:`_composite_ray_ti`'s loop inlined (same arithmetic)."""
    i = wp.tid()
    r = int(rays[i])
    T = float(transmittance[r])
    c = color[r]
    a = float(opacity[r])
    z = float(depth[r])
    s = int(ray_offsets[i])
    end = ray_offsets[i + 1]
    while s < end and T >= threshold:
        alpha = 1.0 - wp.exp(-sigmas[s] * deltas[s])
        weight = T * alpha
        c += weight * colors[s]
        a += weight
        z += weight * depths[s]
        T *= 1.0 - alpha
        s += 1
    transmittance[r] = T
    color[r] = c
    opacity[r] = a
    depth[r] = z


@wp.kernel
def _gather_ray_rows_wp(
    table: wp.array2d(dtype=wp.int32),
    rays: wp.array(dtype=wp.int64),
    slots: wp.array(dtype=wp.int64),
    per_ray: int,
    out: wp.array2d(dtype=wp.int32),
):
    s, c = wp.tid()
    out[s, c] = table[int(rays[int(slots[s]) // per_ray]), c]


def gather_ray_rows(
    table: torch.Tensor, rays: torch.Tensor, slots: torch.Tensor, samples_per_ray: int, *, kernel: bool | None = None
) -> torch.Tensor:
    """Each sample's row of a per-ray table: row ``rays[slots[s] // k]`` of ``table`` for every slot ``s`` of a round
    (:class:`RoundSamples`: ray ``i`` of the round owns slots ``i k … i k + k − 1``), e.g. the encoded view direction
    of each shaded sample's ray.

    Args:
        table: ``[R, C]``; for the kernel contiguous, rows of whole 4-byte words (e.g. float16 with even ``C``).
        rays: int64 ``[A]`` the round's rays (indices into ``table``).
        slots: int64 ``[S]`` slots of the round's ``[A · k]``.
        samples_per_ray: ``k``.
        kernel: copy the rows' words with a Warp kernel, or ``False``: torch indexing. ``None``: the kernel on
            CUDA (for rows of whole words), where it is several times faster than torch's gather
            (``docs/benchmarks.md``); torch indexing on the CPU.

    Returns:
        ``[S, C]`` of ``table``'s dtype.
    """
    if samples_per_ray < 1 or rays.dtype != torch.int64 or slots.dtype != torch.int64:
        raise ValueError("need samples_per_ray >= 1 and int64 rays and slots")
    whole_words = table.dim() == 2 and table.is_contiguous() and (table.shape[1] * table.element_size()) % 4 == 0
    if kernel is None:
        kernel = table.device.type == "cuda" and whole_words
    if not kernel:
        return table[rays[slots // samples_per_ray]]
    if not whole_words:
        raise ValueError(
            f"table must be a contiguous [R, C] of whole 4-byte rows, got {table.dtype} {list(table.shape)}"
        )
    out = torch.empty(slots.shape[0], table.shape[1], dtype=table.dtype, device=table.device)
    words = table.shape[1] * table.element_size() // 4
    if out.numel() > 0:
        wp.launch(
            _gather_ray_rows_wp,
            dim=(slots.shape[0], words),
            inputs=[
                backend.warp_arg(table.view(torch.int32).view(-1, words)),
                backend.warp_arg(rays.contiguous()),
                backend.warp_arg(slots.contiguous()),
                int(samples_per_ray),
                backend.warp_arg(out.view(torch.int32).view(-1, words)),
            ],
            device=backend.warp_device(),
        )
    return out


class CompositeState(NamedTuple):
    """Running compositing sums of rays composited in rounds (:func:`composite_start`, :func:`composite_accumulate`).

    Attributes:
        color: float32 ``[R, 3]`` ``Σ w_i c_i`` (premultiplied colour).
        opacity: float32 ``[R]`` ``Σ w_i``.
        depth: float32 ``[R]`` ``Σ w_i t_i``, metres.
        transmittance: float32 ``[R]`` ``T`` after the samples composited so far.
    """

    color: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    transmittance: torch.Tensor


def composite_start(rays: int, device: torch.device | str) -> CompositeState:
    """Sums of ``rays`` rays before any sample: no colour, opacity or depth, transmittance 1."""
    return CompositeState(
        torch.zeros(rays, 3, device=device),
        torch.zeros(rays, device=device),
        torch.zeros(rays, device=device),
        torch.ones(rays, device=device),
    )


def composite_accumulate(
    state: CompositeState,
    rays: torch.Tensor,
    sigmas: torch.Tensor,
    colors: torch.Tensor,
    deltas: torch.Tensor,
    depths: torch.Tensor,
    ray_offsets: torch.Tensor,
    *,
    transmittance_threshold: float = DEFAULT_TRANSMITTANCE_THRESHOLD,
    framework: str | None = None,
) -> None:
    """Composite the next packed samples of rays ``rays`` onto their running sums in ``state`` (in place; forward
    only, for rendering).

    Each ray carries on exactly where its earlier rounds stopped, with :func:`composite_forward`'s arithmetic, so
    compositing a ray's samples in consecutive rounds gives the very sums one :func:`composite_forward` call over
    all of them gives, early termination included (a ray whose transmittance is below the threshold takes no more
    samples).

    Args:
        state: from :func:`composite_start` (``R`` rays).
        rays: int64 ``[A]`` distinct indices into the state of the rays composited here.
        sigmas, colors, deltas, depths: ``[S]``, ``[S, 3]``, ``[S]``, ``[S]`` packed samples (as
            :func:`composite_forward`).
        ray_offsets: int32 ``[A + 1]``: ray ``rays[i]`` owns samples ``ray_offsets[i]:ray_offsets[i + 1]``.
        transmittance_threshold: a ray stops at the first sample with ``T`` below this.
        framework: ``"taichi"`` or ``"warp"`` (the same loop); ``None``: :func:`kernels.backend.default_framework`.
    """
    marched = _check_samples(sigmas, colors, deltas, depths, ray_offsets)
    framework = backend.check_framework(framework)
    if not (isinstance(rays, torch.Tensor) and rays.dtype == torch.int64 and rays.shape == (marched,)):
        raise ValueError(
            f"rays must be int64 [A] = [{marched}] (one per CSR row), got "
            f"{getattr(rays, 'dtype', None)} {list(getattr(rays, 'shape', []))}"
        )
    total = state.opacity.shape[0]
    for name, tensor, shape in (
        ("color", state.color, (total, 3)),
        ("opacity", state.opacity, (total,)),
        ("depth", state.depth, (total,)),
        ("transmittance", state.transmittance, (total,)),
    ):
        if tensor.dtype != torch.float32 or tensor.shape != shape or not tensor.is_contiguous():
            raise ValueError(f"state.{name} must be contiguous float32 {list(shape)}; build it with composite_start")
    if marched > 0 and framework == "warp":
        inputs = (sigmas, colors, deltas, depths, ray_offsets, rays)
        wp.launch(
            _composite_accumulate_wp,
            dim=marched,
            inputs=[
                *_warp_views(t.detach().contiguous() for t in inputs),
                float(transmittance_threshold),
                *_warp_views(state),
            ],
            device=backend.warp_device(),
        )
    elif marched > 0:
        _composite_accumulate_ti(
            *(backend.taichi_arg(t.detach().contiguous()) for t in (sigmas, colors, deltas, depths, ray_offsets)),
            backend.taichi_arg(rays.contiguous()),
            float(transmittance_threshold),
            *(backend.taichi_arg(t) for t in state),
            torch.empty(0, device=sigmas.device),
        )


@ti.kernel
def _composite_backward_ti(
    grad_color: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    grad_opacity: ti.types.ndarray(dtype=ti.f32, ndim=1),
    grad_depth: ti.types.ndarray(dtype=ti.f32, ndim=1),
    sigmas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    deltas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    depths: ti.types.ndarray(dtype=ti.f32, ndim=1),
    ray_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    out_color: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    out_opacity: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out_depth: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out_used: ti.types.ndarray(dtype=ti.i32, ndim=1),
    grad_sigmas: ti.types.ndarray(dtype=ti.f32, ndim=1),
    grad_colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
):
    for r in range(ray_offsets.shape[0] - 1):
        g_color, g_opacity, g_depth = grad_color[r], grad_opacity[r], grad_depth[r]
        total_color, total_opacity, total_depth = out_color[r], out_opacity[r], out_depth[r]
        transmittance = 1.0
        color = ti.math.vec3(0.0)
        opacity, depth = 0.0, 0.0
        start = ray_offsets[r]
        for i in range(start, start + out_used[r]):
            alpha = 1.0 - ti.exp(-sigmas[i] * deltas[i])
            weight = transmittance * alpha
            color += weight * colors[i]
            opacity += weight
            depth += weight * depths[i]
            transmittance *= 1.0 - alpha  # now T_{i+1}
            # ∂/∂σ_i of each output: δ_i (T_{i+1} x_i − (total − running sum up to i)).
            d_color = transmittance * colors[i] - (total_color - color)
            d_opacity = transmittance - (total_opacity - opacity)
            d_depth = transmittance * depths[i] - (total_depth - depth)
            grad_sigmas[i] = deltas[i] * (g_color.dot(d_color) + g_opacity * d_opacity + g_depth * d_depth)
            grad_colors[i] = weight * g_color


def composite_backward(
    grad_color: torch.Tensor,
    grad_opacity: torch.Tensor,
    grad_depth: torch.Tensor,
    sigmas: torch.Tensor,
    colors: torch.Tensor,
    deltas: torch.Tensor,
    depths: torch.Tensor,
    ray_offsets: torch.Tensor,
    color: torch.Tensor,
    opacity: torch.Tensor,
    depth: torch.Tensor,
    used: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradients of a loss with respect to σ_i and c_i from the forward outputs (module docstring).

    Args:
        grad_color, grad_opacity, grad_depth: float32 ``[R, 3]``, ``[R]``, ``[R]`` incoming gradients.
        sigmas, colors, deltas, depths, ray_offsets: the inputs of :func:`composite_forward`.
        color, opacity, depth, used: its outputs.

    Returns:
        ``(grad_sigmas [S], grad_colors [S, 3])``, zero for samples after termination.
    """
    rays = _check_samples(sigmas, colors, deltas, depths, ray_offsets)
    for name, tensor, shape in (
        ("grad_color", grad_color, (rays, 3)),
        ("grad_opacity", grad_opacity, (rays,)),
        ("grad_depth", grad_depth, (rays,)),
    ):
        if tensor.shape != shape or tensor.dtype != torch.float32:
            raise ValueError(f"{name} must be float32 {list(shape)}, got {tensor.dtype} {list(tensor.shape)}")
    grad_sigmas = torch.zeros_like(sigmas)
    grad_colors = torch.zeros_like(colors)
    if rays > 0:
        tensors = (grad_color, grad_opacity, grad_depth, sigmas, colors, deltas, depths, ray_offsets)
        tensors += (color, opacity, depth, used, grad_sigmas, grad_colors)
        _composite_backward_ti(*(backend.taichi_arg(t.detach().contiguous()) for t in tensors))
    return grad_sigmas, grad_colors


class VolumeRenderFunction(torch.autograd.Function):
    """Differentiable compositing: ``apply(sigmas, colors, deltas, depths, ray_offsets, threshold, return_weights)``.

    Returns ``(color [R, 3], opacity [R], depth [R], weights [S])``; σ and c receive gradients from
    :func:`composite_backward`. ``weights`` is empty unless asked for and is not differentiable.
    """

    @staticmethod
    def forward(ctx, sigmas, colors, deltas, depths, ray_offsets, threshold, return_weights):
        color, opacity, depth, used, weights = composite_forward(
            sigmas,
            colors,
            deltas,
            depths,
            ray_offsets,
            transmittance_threshold=threshold,
            return_weights=return_weights,
        )
        if weights is None:
            weights = torch.empty(0, device=sigmas.device)
        ctx.save_for_backward(sigmas, colors, deltas, depths, ray_offsets, color, opacity, depth, used)
        ctx.mark_non_differentiable(weights)
        return color, opacity, depth, weights

    @staticmethod
    def backward(ctx, grad_color, grad_opacity, grad_depth, grad_weights):
        sigmas, colors, deltas, depths, ray_offsets, color, opacity, depth, used = ctx.saved_tensors
        grads = [
            torch.zeros_like(reference) if g is None else g.contiguous()
            for g, reference in ((grad_color, color), (grad_opacity, opacity), (grad_depth, depth))
        ]
        grad_sigmas, grad_colors = composite_backward(
            *grads, sigmas, colors, deltas, depths, ray_offsets, color, opacity, depth, used
        )
        return grad_sigmas, grad_colors, None, None, None, None, None


def composite(
    sigmas: torch.Tensor,
    colors: torch.Tensor,
    deltas: torch.Tensor,
    depths: torch.Tensor,
    ray_offsets: torch.Tensor,
    *,
    transmittance_threshold: float = DEFAULT_TRANSMITTANCE_THRESHOLD,
    return_weights: bool = False,
) -> dict[str, torch.Tensor]:
    """Differentiable :func:`composite_forward` (arguments as there).

    Returns:
        ``{"color": [R, 3], "opacity": [R], "depth": [R]}`` and ``"weights": [S]`` when asked for; σ and c
        receive gradients through :class:`VolumeRenderFunction`.
    """
    color, opacity, depth, weights = VolumeRenderFunction.apply(
        sigmas, colors, deltas, depths, ray_offsets, float(transmittance_threshold), bool(return_weights)
    )
    out = {"color": color, "opacity": opacity, "depth": depth}
    if return_weights:
        out["weights"] = weights
    return out


# ---------------------------------------------------------------------------------------------------
# Argument checks
# ---------------------------------------------------------------------------------------------------


def _check_rays(origins: torch.Tensor, directions: torch.Tensor) -> int:
    for name, tensor in (("origins", origins), ("directions", directions)):
        if not isinstance(tensor, torch.Tensor) or tensor.dtype != torch.float32:
            raise TypeError(f"{name} must be a float32 tensor [R, 3]; convert it with .float()")
        if tensor.dim() != 2 or tensor.shape[1] != 3:
            raise ValueError(f"{name} must be [R, 3], got {tuple(tensor.shape)}")
    if origins.shape != directions.shape:
        raise ValueError(f"origins {tuple(origins.shape)} and directions {tuple(directions.shape)} differ in shape")
    return origins.shape[0]


def _check_occupancy(occupancy: torch.Tensor) -> torch.Tensor:
    """The grid as contiguous uint8 (a no-op for a uint8 grid)."""
    if (
        not isinstance(occupancy, torch.Tensor)
        or occupancy.dim() != 3
        or occupancy.dtype not in (torch.bool, torch.uint8)
    ):
        raise ValueError(
            f"occupancy must be a [Gx, Gy, Gz] bool or uint8 grid, got {getattr(occupancy, 'dtype', None)} "
            f"{tuple(getattr(occupancy, 'shape', ()))}"
        )
    return occupancy.to(torch.uint8).contiguous()


def _box(aabb, framework: str = "taichi") -> tuple:
    """``(lo, hi)`` of a ``[2, 3]`` box as Taichi or Warp vectors (a CPU box costs no device transfer)."""
    aabb = torch.as_tensor(aabb, dtype=torch.float32).cpu()
    if aabb.shape != (2, 3):
        raise ValueError(f"aabb must be [2, 3] (lo, hi), got shape {tuple(aabb.shape)}")
    return _box_vectors(tuple(aabb.flatten().tolist()), framework)


@functools.lru_cache(maxsize=64)
def _box_vectors(corners: tuple, framework: str) -> tuple:
    """Vectors of a box's corners, cached: building Taichi's costs more than a round's launch of a kernel."""
    lo, hi = corners[:3], corners[3:]
    if not all(h > l for l, h in zip(lo, hi, strict=True)):
        raise ValueError(f"aabb must be [2, 3] (lo, hi) with hi > lo on every axis, got {[list(lo), list(hi)]}")
    vector = wp.vec3 if framework == "warp" else ti.math.vec3
    return vector(lo), vector(hi)


def _warp_views(tensors) -> list:
    """Zero-copy Warp launch arguments of tensors (:func:`kernels.backend.warp_arg`): ``[N, 3]`` float32 as ``vec3``
    arrays, the others by their scalar type."""
    return [
        backend.warp_arg(t, dtype=wp.vec3 if t.dim() == 2 and t.shape[1] == 3 and t.dtype == torch.float32 else None)
        for t in tensors
    ]


def _steps(min_step: float, max_step: float | None, cone_angle: float, max_samples: int) -> tuple:
    """``(min_step, max_step, cone_angle, max_samples)`` checked, with the default ``max_step`` filled in."""
    if cone_angle < 0.0 or not min_step > 0.0:
        raise ValueError(f"need min_step > 0 and cone_angle >= 0, got min_step={min_step}, cone_angle={cone_angle}")
    if max_step is None:
        max_step = 1e10 if cone_angle > 0.0 else min_step
    if max_step < min_step:
        raise ValueError(f"max_step ({max_step}) must be at least min_step ({min_step})")
    if max_samples < 1:
        raise ValueError(f"max_samples must be at least 1, got {max_samples}")
    return float(min_step), float(max_step), float(cone_angle), int(max_samples)


def _per_ray(value, rays: int, name: str, device: torch.device) -> torch.Tensor:
    tensor = torch.as_tensor(value, dtype=torch.float32, device=device)
    if tensor.dim() == 0:
        return tensor.expand(rays).contiguous()
    if tensor.shape != (rays,):
        raise ValueError(f"{name} must be a scalar or [R] = [{rays}], got {tuple(tensor.shape)}")
    return tensor.contiguous()


def _check_samples(sigmas, colors, deltas, depths, ray_offsets) -> int:
    samples = sigmas.shape[0] if isinstance(sigmas, torch.Tensor) and sigmas.dim() == 1 else -1
    for name, tensor, shape in (
        ("sigmas", sigmas, (samples,)),
        ("colors", colors, (samples, 3)),
        ("deltas", deltas, (samples,)),
        ("depths", depths, (samples,)),
    ):
        if not isinstance(tensor, torch.Tensor) or tensor.dtype != torch.float32:
            raise TypeError(f"{name} must be a float32 tensor; convert it with .float()")
        if tensor.shape != shape:
            raise ValueError(f"{name} must be {list(shape)} (S = samples), got {list(tensor.shape)}")
    if not isinstance(ray_offsets, torch.Tensor) or ray_offsets.dtype != torch.int32 or ray_offsets.dim() != 1:
        raise TypeError("ray_offsets must be an int32 tensor [R + 1] (CSR offsets); convert it with .int()")
    if ray_offsets.shape[0] < 1:
        raise ValueError("ray_offsets must hold at least one entry (R + 1 >= 1)")
    if ray_offsets.device.type == "cpu" and (
        int(ray_offsets[0]) != 0 or int(ray_offsets[-1]) != samples or bool((ray_offsets.diff() < 0).any())
    ):
        raise ValueError(
            f"ray_offsets must rise from 0 to S = {samples} (CSR offsets of packed samples), "
            f"got first {int(ray_offsets[0])}, last {int(ray_offsets[-1])}"
        )
    return ray_offsets.shape[0] - 1
