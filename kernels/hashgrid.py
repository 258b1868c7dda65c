"""Multiresolution hash encoding (Müller et al. 2022, instant-NGP), the NeRF encoding of PIE-NeRF §3.1.

A point ``x`` in the unit cube is encoded on ``L`` grids of growing resolution ``N_l`` (Eq. 2, 3). On
level ``l`` the eight vertices of the cell holding ``x * N_l`` index a table of ``T`` feature vectors of
``F`` floats: directly when the level's ``(N_l + 1)^3`` vertices fit in the table, else through the
spatial hash of Eq. 4. The eight vectors are blended trilinearly and the ``L`` results are concatenated
into ``[N, L * F]`` features, level-major within a row (``out[n, l * F + f]``).

Conventions:

* Positions are clamped to ``[0, 1]^3`` first: a point outside the cube gets the features of the
  nearest point of the cube's surface (the caller normalises its scene box to the unit cube).
* The gradient flows to the table only. ``dL/dx`` (the encoding's spatial derivative) is not
  implemented: the autograd function refuses positions that require a gradient.
* The hash works in ``uint32`` arithmetic (products wrap modulo ``2^32``), as in the paper.
* The table the forward pass gathers from is float32 or float16 (:attr:`HashGridConfig.table_dtype`); either way
  the interpolation is float32 and so are the features. A float16 table halves the bytes of a gathered row (4 B at
  ``F = 2``, one 32-bit load on Warp) and the table's footprint in the L2 cache (32 MB at 16 levels of ``2^19`` rows,
  which fits an H100's or H200's 50 MB L2, where the float32 table's 64 MB does not). Training keeps the float32
  table as the parameter (master copy), its gradient and the optimiser's state float32, and
  :class:`HashGridEncoding` rounds it into the float16 copy once after each change: the rounding then never
  accumulates over steps, and updates smaller than float16's spacing are not lost.

Both frameworks are kept, because the faster one depends on the device: on the CPU Taichi runs on every core and
Warp on one; on CUDA the Warp kernels are faster (figures in ``docs/benchmarks.md``): their threads run level by
level, so the blocks in flight share one level's table in L2, the forward pass writes its features feature-major
(coalesced) and the backward pass adds two features with one vector reduction. :func:`default_framework` therefore
picks Taichi on the CPU and Warp on CUDA.
"""

import functools
import math
from dataclasses import dataclass

import taichi as ti
import torch
import warp as wp

from kernels import backend

__all__ = [
    "FRAMEWORKS",
    "HASH_PRIMES",
    "HashGridConfig",
    "HashGridEncoding",
    "HashGridFunction",
    "TABLE_DTYPES",
    "default_framework",
    "hashgrid_backward",
    "hashgrid_forward",
    "level_resolutions",
]

FRAMEWORKS = backend.FRAMEWORKS
default_framework = backend.default_framework

HASH_PRIMES = (1, 2654435761, 805459861)
"""The per-axis factors ``pi_i`` of the spatial hash (Eq. 4); ``pi_1 = 1`` keeps x-neighbours adjacent."""

TABLE_DTYPES = {"float32": torch.float32, "float16": torch.float16}
"""The storage types :attr:`HashGridConfig.table_dtype` names, with their torch dtypes."""

_MAX_TABLE_SIZE = 2**31 - 1
_MAX_THREADS = 2**31 - 1


def level_resolutions(levels: int, base_resolution: int, max_resolution: int) -> torch.Tensor:
    """Grid resolution of every level, ``N_l = floor(N_min * b^l)`` (Eq. 2) with ``b`` from Eq. 3.

    ``b = exp((ln N_max - ln N_min) / (L - 1))`` is the growth factor between levels, so the finest
    level has ``N_max`` cells per unit length. A tolerance of ``1e-9`` relative keeps rounding in
    ``b^l`` from dropping an exact integer (``N_{L-1} = N_max``) to the one below.

    Args:
        levels: ``L >= 1``.
        base_resolution: ``N_min >= 1``, cells per unit length of the coarsest level.
        max_resolution: ``N_max >= N_min``, cells per unit length of the finest level.

    Returns:
        int32 tensor ``[L]`` on the CPU.
    """
    if levels < 1 or base_resolution < 1 or max_resolution < base_resolution:
        raise ValueError(
            f"need levels >= 1 and 1 <= base_resolution <= max_resolution, got levels={levels}, "
            f"base_resolution={base_resolution}, max_resolution={max_resolution}"
        )
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (levels - 1)) if levels > 1 else 1.0
    values = [math.floor(base_resolution * growth**level * (1.0 + 1e-9)) for level in range(levels)]
    return torch.tensor(values, dtype=torch.int32)


def _level_major() -> bool:
    """Thread order of the Taichi kernels on the initialised device (the Warp kernels are level-major everywhere).

    CPU: level-major, so one level's table (4 MB at ``T = 2^19``) stays in cache while all points
    visit it, and the Taichi backward gives each level to one task (no atomics). CUDA: point-major,
    so the 32 threads of a warp write 2 whole rows of Taichi's row-major output (coalesced).
    """
    return backend.current_device() == "cpu"


# ---------------------------------------------------------------------------------------------------
# Warp
# ---------------------------------------------------------------------------------------------------

_PI_Y = wp.constant(wp.uint32(HASH_PRIMES[1]))
_PI_Z = wp.constant(wp.uint32(HASH_PRIMES[2]))


@wp.func
def _spatial_hash_wp(vertex: wp.vec3i, table_size: wp.uint32) -> wp.int32:
    """Eq. 4: ``h(v) = (v_x * 1 XOR v_y * pi_2 XOR v_z * pi_3) mod T`` in uint32 arithmetic."""
    h = wp.uint32(vertex[0]) ^ (wp.uint32(vertex[1]) * _PI_Y) ^ (wp.uint32(vertex[2]) * _PI_Z)
    if (table_size & (table_size - wp.uint32(1))) == wp.uint32(0):
        return wp.int32(h & (table_size - wp.uint32(1)))  # a power of two: mod is a mask, no division
    return wp.int32(h % table_size)


@wp.func
def _vertex_index_wp(vertex: wp.vec3i, resolution: wp.int32, dense: wp.bool, table_size: wp.int32) -> wp.int32:
    """Table row of a grid vertex: row-major ``x + (N+1) (y + (N+1) z)`` on a dense level, else Eq. 4."""
    if dense:
        side = resolution + 1
        return vertex[0] + side * (vertex[1] + side * vertex[2])
    return _spatial_hash_wp(vertex, wp.uint32(table_size))


@wp.func
def _is_dense_wp(resolution: wp.int32, table_size: wp.int32) -> wp.bool:
    """Whether all ``(N + 1)^3`` vertices of the level fit in the table (int64: ``2049^3`` exceeds int32)."""
    side = wp.int64(resolution + 1)
    return side * side * side <= wp.int64(table_size)


@wp.func
def _cell_wp(x: wp.vec3, resolution: wp.int32):
    """Cell ``floor(x N)`` (clamped to ``[0, N-1]``) and local coordinates in it, for ``x`` clamped to the cube."""
    scale = wp.float32(resolution)
    cell = wp.vec3i()
    local = wp.vec3()
    for axis in range(3):
        p = wp.clamp(x[axis], 0.0, 1.0) * scale
        c = wp.clamp(wp.int32(wp.floor(p)), 0, resolution - 1)
        cell[axis] = c
        local[axis] = p - wp.float32(c)
    return cell, local


@wp.func
def _corner_wp(corner: wp.int32, local: wp.vec3):
    """Offset ``{0,1}^3`` of cell corner ``corner`` (bit a = axis a) and its trilinear weight.

    The weight is ``prod_a (o_a ? u_a : 1 - u_a)`` for local coordinates ``u``: the d-linear
    interpolation of Müller et al. 2022 §3 with d = 3.
    """
    offset = wp.vec3i(corner & 1, (corner >> 1) & 1, (corner >> 2) & 1)
    weight = wp.float32(1.0)
    for axis in range(3):
        if offset[axis] == 1:
            weight *= local[axis]
        else:
            weight *= 1.0 - local[axis]
    return offset, weight


_RED_ADD_PAIR = """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
    asm volatile("red.global.add.v2.f32 [%0], {%1, %2};" :: "l"(&grad[index]), "f"(a), "f"(b) : "memory");
#elif defined(__CUDA_ARCH__)
    atomicAdd(&grad[index], a);
    atomicAdd(&grad[index + 1], b);
#else
    wp::atomic_add(&grad[index], a);
    wp::atomic_add(&grad[index + 1], b);
#endif
"""


@wp.func_native(_RED_ADD_PAIR)
def _red_add_pair_wp(grad: wp.array(dtype=wp.float32), index: wp.int32, a: wp.float32, b: wp.float32):
    """``grad[index] += a; grad[index + 1] += b`` atomically; ``index`` even (8-byte aligned).

    On sm_90 and later one vector reduction (``red.global.add.v2.f32``) adds both: the L2 cache then does half
    as many atomic operations, which halves the backward pass (``docs/benchmarks.md``).
    """
    ...


_HALF2_TO_VEC2 = """
wp::half lo, hi;
lo.u = static_cast<unsigned short>(bits & 0xFFFFu);
hi.u = static_cast<unsigned short>(bits >> 16);
return wp::vec2(wp::half_to_float(lo), wp::half_to_float(hi));
"""


@wp.func_native(_HALF2_TO_VEC2)
def _half2_to_vec2_wp(bits: wp.uint32) -> wp.vec2:
    """The two float16 of one 32-bit word as float32, the one at the lower address (the low 16 bits, little-endian)
    first: a ``half2``, i.e. two features of a float16 table row read with one 32-bit load."""
    ...


@functools.cache
def _forward_kernel_wp(features: int, storage: str = "float32"):
    """Forward Warp kernel for ``features`` floats per row: thread ``(level, i)``, output feature-major ``[L F, N]``.

    Level-major threads: the blocks in flight read one level's table, which stays in L2 (a 2^19-row level is 4 MB,
    all 16 levels 64 MB); the feature-major output lets a warp's 32 threads write 32 consecutive floats.

    ``storage`` is how the table arrives: ``"float32"`` (``[L, T]`` rows of ``F`` floats, one vector load per row),
    ``"half2"`` (a float16 table with ``F`` even, seen as ``[L, T, F / 2]`` 32-bit words: one load per feature pair,
    half the bytes per gathered row) or ``"float16"`` (``[L, T, F]`` float16, ``F`` odd). Interpolation is float32
    in all three.
    """
    vec = wp.types.vector(length=features, dtype=wp.float32)
    table_type = {
        "float32": wp.array2d(dtype=vec),
        "half2": wp.array3d(dtype=wp.uint32),
        "float16": wp.array3d(dtype=wp.float16),
    }[storage]
    pairs = features // 2

    @wp.kernel(enable_backward=False, module="unique")
    def _hashgrid_forward_wp(
        x: wp.array(dtype=wp.vec3),
        table: table_type,
        resolutions: wp.array(dtype=wp.int32),
        out: wp.array2d(dtype=wp.float32),
    ):
        level, i = wp.tid()
        resolution = resolutions[level]
        table_size = table.shape[1]
        dense = _is_dense_wp(resolution, table_size)
        cell, local = _cell_wp(x[i], resolution)
        acc = vec()
        for corner in range(8):
            offset, weight = _corner_wp(corner, local)
            row = _vertex_index_wp(cell + offset, resolution, dense, table_size)
            if wp.static(storage == "float32"):
                acc += weight * table[level, row]
            elif wp.static(storage == "half2"):
                for k in range(pairs):
                    pair = _half2_to_vec2_wp(table[level, row, k])
                    acc[2 * k] += weight * pair[0]
                    acc[2 * k + 1] += weight * pair[1]
            else:
                for f in range(features):
                    acc[f] += weight * wp.float32(table[level, row, f])
        for f in range(features):
            out[level * features + f, i] = acc[f]

    return _hashgrid_forward_wp, vec


@functools.cache
def _backward_kernel_wp(features: int):
    """Backward Warp kernel (atomic scatter-add into the flat ``[L T F]`` gradient), thread ``(level, i)``.

    Level-major, as the forward pass, so that one level's gradient rows take the atomics in L2; features are added
    in pairs by :func:`_red_add_pair_wp` when ``F`` is even, one by one otherwise.
    """
    pairs = features // 2 if features % 2 == 0 else 0

    @wp.kernel(enable_backward=False, module="unique")
    def _hashgrid_backward_wp(
        x: wp.array(dtype=wp.vec3),
        grad_out: wp.array2d(dtype=wp.float32),
        resolutions: wp.array(dtype=wp.int32),
        grad_table: wp.array(dtype=wp.float32),
        table_size: wp.int32,
    ):
        level, i = wp.tid()
        resolution = resolutions[level]
        dense = _is_dense_wp(resolution, table_size)
        cell, local = _cell_wp(x[i], resolution)
        first = level * features
        for corner in range(8):
            offset, weight = _corner_wp(corner, local)
            row = _vertex_index_wp(cell + offset, resolution, dense, table_size)
            base = (level * table_size + row) * features
            if pairs > 0:
                for k in range(pairs):
                    a = weight * grad_out[i, first + 2 * k]
                    b = weight * grad_out[i, first + 2 * k + 1]
                    _red_add_pair_wp(grad_table, base + 2 * k, a, b)
            else:
                for f in range(features):
                    wp.atomic_add(grad_table, base + f, weight * grad_out[i, first + f])

    return _hashgrid_backward_wp


# ---------------------------------------------------------------------------------------------------
# Taichi
# ---------------------------------------------------------------------------------------------------


@ti.func
def _spatial_hash_ti(vertex, table_size: ti.i32) -> ti.i32:
    """Eq. 4: ``h(v) = (v_x * 1 XOR v_y * pi_2 XOR v_z * pi_3) mod T`` in uint32 arithmetic."""
    v = ti.cast(vertex, ti.u32)
    h = v[0] ^ (v[1] * ti.u32(HASH_PRIMES[1])) ^ (v[2] * ti.u32(HASH_PRIMES[2]))
    size = ti.cast(table_size, ti.u32)
    row = ti.u32(0)
    if size & (size - 1) == 0:
        row = h & (size - 1)  # a power of two: mod is a mask, no division
    else:
        row = h % size
    return ti.cast(row, ti.i32)


@ti.func
def _vertex_index_ti(vertex, resolution: ti.i32, dense: ti.i32, table_size: ti.i32) -> ti.i32:
    """Table row of a grid vertex: row-major ``x + (N+1) (y + (N+1) z)`` on a dense level, else Eq. 4."""
    row = 0
    if dense:
        side = resolution + 1
        row = vertex[0] + side * (vertex[1] + side * vertex[2])
    else:
        row = _spatial_hash_ti(vertex, table_size)
    return row


@ti.func
def _is_dense_ti(resolution: ti.i32, table_size: ti.i32) -> ti.i32:
    """Whether all ``(N + 1)^3`` vertices of the level fit in the table (int64: ``2049^3`` exceeds int32)."""
    side = ti.cast(resolution + 1, ti.i64)
    return ti.cast(side * side * side <= ti.cast(table_size, ti.i64), ti.i32)


@ti.func
def _cell_ti(x, resolution: ti.i32):
    """Cell ``floor(x N)`` (clamped to ``[0, N-1]``) and local coordinates in it, for ``x`` clamped to the cube."""
    p = ti.math.clamp(x, 0.0, 1.0) * ti.cast(resolution, ti.f32)
    cell = ti.math.clamp(ti.cast(ti.floor(p), ti.i32), 0, resolution - 1)
    return cell, p - ti.cast(cell, ti.f32)


@ti.func
def _corner_ti(corner: ti.template(), local):
    """Offset ``{0,1}^3`` of cell corner ``corner`` (bit a = axis a) and its trilinear weight."""
    offset = ti.Vector([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])
    weight = 1.0
    for axis in ti.static(range(3)):
        weight *= local[axis] if offset[axis] == 1 else 1.0 - local[axis]
    return offset, weight


@ti.kernel
def _hashgrid_forward_ti(
    x: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    table: ti.types.ndarray(ndim=3),  # f32 or f16 (one compiled kernel each), interpolated in f32
    resolutions: ti.types.ndarray(dtype=ti.i32, ndim=1),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    features: ti.template(),
    level_major: ti.template(),
):
    table_size = table.shape[1]
    points, levels = x.shape[0], resolutions.shape[0]
    for j in range(points * levels):
        i, level = j // levels, j % levels
        if ti.static(level_major):
            i, level = j % points, j // points
        resolution = resolutions[level]
        dense = _is_dense_ti(resolution, table_size)
        cell, local = _cell_ti(x[i], resolution)
        acc = ti.Vector.zero(ti.f32, features)
        for corner in ti.static(range(8)):
            offset, weight = _corner_ti(corner, local)
            row = _vertex_index_ti(cell + offset, resolution, dense, table_size)
            for f in ti.static(range(features)):
                acc[f] += weight * ti.cast(table[level, row, f], ti.f32)
        for f in ti.static(range(features)):
            out[i, level * features + f] = acc[f]


@ti.func
def _scatter_ti(
    x: ti.template(),
    grad_out: ti.template(),
    resolutions: ti.template(),
    grad_table: ti.template(),
    features: ti.template(),
    i: ti.i32,
    level: ti.i32,
    atomic: ti.template(),
):
    """Add point ``i``'s feature gradient on ``level``, weighted trilinearly, to the 8 rows it read."""
    table_size = grad_table.shape[1]
    resolution = resolutions[level]
    dense = _is_dense_ti(resolution, table_size)
    cell, local = _cell_ti(x[i], resolution)
    g = ti.Vector([grad_out[i, level * features + f] for f in ti.static(range(features))])
    for corner in ti.static(range(8)):
        offset, weight = _corner_ti(corner, local)
        row = _vertex_index_ti(cell + offset, resolution, dense, table_size)
        for f in ti.static(range(features)):
            if ti.static(atomic):
                ti.atomic_add(grad_table[level, row, f], weight * g[f])
            else:
                grad_table[level, row, f] = grad_table[level, row, f] + weight * g[f]


@ti.kernel
def _hashgrid_backward_ti(
    x: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    grad_out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    resolutions: ti.types.ndarray(dtype=ti.i32, ndim=1),
    grad_table: ti.types.ndarray(dtype=ti.f32, ndim=3),
    features: ti.template(),
    level_major: ti.template(),
):
    if ti.static(level_major):
        # One task per level: a task owns its level's rows, so plain adds replace atomics.
        for level in range(resolutions.shape[0]):
            for i in range(x.shape[0]):
                _scatter_ti(x, grad_out, resolutions, grad_table, features, i, level, False)
    else:
        for i, level in ti.ndrange(x.shape[0], resolutions.shape[0]):
            _scatter_ti(x, grad_out, resolutions, grad_table, features, i, level, True)


# ---------------------------------------------------------------------------------------------------
# Host functions
# ---------------------------------------------------------------------------------------------------


def hashgrid_forward(
    x: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, *, framework: str | None = None
) -> torch.Tensor:
    """Encode points on a multiresolution hash grid (Eq. 2-4 and trilinear interpolation).

    Args:
        x: float32 ``[N, 3]`` positions in the unit cube (clamped to ``[0, 1]^3``), on the backend device.
        table: float32 or float16 ``[L, T, F]`` feature table, ``T`` rows of ``F`` features per level. A float16
            table is read as such (half the bytes per gathered row; on Warp with ``F`` even, one 32-bit load per
            feature pair) and interpolated in float32.
        resolutions: integer ``[L]`` grid resolutions ``N_l`` in cells per unit length
            (:func:`level_resolutions`), on any device; values are checked when it lives on the CPU.
        framework: ``"taichi"`` or ``"warp"``; ``None`` takes :func:`default_framework`.

    Returns:
        float32 ``[N, L * F]`` features, ``out[n, l * F + f]``. Warp writes them feature-major and returns the
        transposed view (strides ``(1, N)``), which ``torch.nn.Linear`` and matmul read without a copy; call
        ``.contiguous()`` where row-major storage is needed.
    """
    framework = backend.check_framework(framework)
    levels, table_size, features = _check_table(table, "table")
    resolutions = _check_levels(x, resolutions, levels)
    if framework == "warp":
        if table.dtype == torch.float32:
            storage, warp_table, dtype = "float32", table, None
        elif features % 2 == 0:  # feature pairs as 32-bit words: [L, T, F] float16 -> [L, T, F / 2] uint32
            storage, warp_table, dtype = "half2", table.view(torch.int32), wp.uint32
        else:
            storage, warp_table, dtype = "float16", table, None
        forward_kernel, vec = _forward_kernel_wp(features, storage)
        out = torch.empty(levels * features, x.shape[0], dtype=torch.float32, device=x.device)
        if x.shape[0] == 0:
            return out.t()
        wp.launch(
            forward_kernel,
            dim=(levels, x.shape[0]),
            inputs=[
                backend.to_warp(x, dtype=wp.vec3),
                backend.to_warp(warp_table, dtype=vec if storage == "float32" else dtype),
                backend.to_warp(resolutions),
                backend.to_warp(out),
            ],
            device=backend.warp_device(),
        )
        return out.t()
    out = torch.empty(x.shape[0], levels * features, dtype=torch.float32, device=x.device)
    if x.shape[0] > 0:
        _hashgrid_forward_ti(
            backend.taichi_arg(x),
            backend.taichi_arg(table),
            backend.taichi_arg(resolutions),
            backend.taichi_arg(out),
            features,
            _level_major(),
        )
    return out


def hashgrid_backward(
    x: torch.Tensor,
    grad_out: torch.Tensor,
    resolutions: torch.Tensor,
    table_size: int,
    *,
    framework: str | None = None,
) -> torch.Tensor:
    """Gradient of a loss with respect to the feature table, by atomic scatter-add of ``grad_out``.

    Each output feature is a trilinear blend of eight table rows, so row ``r`` of level ``l`` receives
    ``sum_n w_nc * grad_out[n, l * F : (l + 1) * F]`` over the points ``n`` and corners ``c`` that map
    to it, hash collisions included.

    Args:
        x: float32 ``[N, 3]`` positions the forward pass encoded.
        grad_out: float32 ``[N, L * F]`` gradient of the loss with respect to the features, row-major or
            feature-major (the transposed view of a contiguous ``[L * F, N]``, strides ``(1, N)``). Feature-major is
            how autograd hands it over in training: :func:`hashgrid_forward` returns its features as such a view on
            Warp, and torch's matrix-product backward returns the gradient of a column-major operand column-major.
            Warp reads it in place, one level's feature for consecutive points from consecutive addresses;
            Taichi takes a row-major copy.
        resolutions: integer ``[L]`` grid resolutions of the forward pass.
        table_size: ``T``, rows per level of the table.
        framework: ``"taichi"`` or ``"warp"``; ``None`` takes :func:`default_framework`.

    Returns:
        float32 ``[L, T, F]`` gradient of the table.
    """
    framework = backend.check_framework(framework)
    if not isinstance(table_size, int) or not 1 <= table_size <= _MAX_TABLE_SIZE:
        raise ValueError(f"table_size must be an int in [1, 2^31 - 1], got {table_size!r}")
    levels = resolutions.shape[0] if isinstance(resolutions, torch.Tensor) and resolutions.dim() == 1 else 0
    resolutions = _check_levels(x, resolutions, levels)
    if not isinstance(grad_out, torch.Tensor) or grad_out.dtype != torch.float32:
        raise TypeError(f"grad_out must be a float32 tensor, got {_describe(grad_out)}; convert it with .float()")
    if grad_out.dim() != 2 or grad_out.shape[0] != x.shape[0] or grad_out.shape[1] % levels != 0:
        raise ValueError(
            f"grad_out must be [N, L * F] with N = {x.shape[0]} points and L = {levels} levels, "
            f"got {tuple(grad_out.shape)}"
        )
    features = grad_out.shape[1] // levels
    if features == 0:
        raise ValueError("grad_out has no features (shape [N, 0]); F must be at least 1")
    if not _row_or_feature_major(grad_out):
        raise ValueError(
            f"grad_out must be row-major [N, L * F] or feature-major (strides (1, N)), got strides "
            f"{grad_out.stride()}; call .contiguous() first"
        )
    grad_table = torch.zeros(levels, table_size, features, dtype=torch.float32, device=x.device)
    if x.shape[0] == 0:
        return grad_table
    if framework == "warp":
        wp.launch(
            _backward_kernel_wp(features),
            dim=(levels, x.shape[0]),
            inputs=[
                backend.to_warp(x, dtype=wp.vec3),
                backend.to_warp(grad_out, strided=True),  # either layout, indexed through its strides
                backend.to_warp(resolutions),
                backend.to_warp(grad_table.view(-1)),
                table_size,
            ],
            device=backend.warp_device(),
        )
    else:
        _hashgrid_backward_ti(
            backend.taichi_arg(x),
            backend.taichi_arg(grad_out.contiguous()),
            backend.taichi_arg(resolutions),
            backend.taichi_arg(grad_table),
            features,
            _level_major(),
        )
    return grad_table


def _row_or_feature_major(grad_out: torch.Tensor) -> bool:
    """``grad_out [N, C]`` is laid out as :func:`hashgrid_backward` reads it: row-major, or the transposed view of a
    contiguous ``[C, N]``."""
    return grad_out.is_contiguous() or grad_out.t().is_contiguous()


class HashGridFunction(torch.autograd.Function):
    """Differentiable encoding: ``HashGridFunction.apply(x, table, resolutions, framework, stored)``.

    The table receives its gradient from :func:`hashgrid_backward`, float32, cast to the table's dtype. Positions
    must not require a gradient: ``dL/dx`` is not implemented (detach ``x``, or differentiate density by finite
    differences).

    ``stored``, optional: the table the kernels read instead of ``table``, of its shape (a float16 copy of a float32
    master table, :class:`HashGridEncoding`); the gradient still goes to ``table``, which the backward never reads.
    """

    @staticmethod
    def forward(ctx, x, table, resolutions, framework=None, stored=None):
        if ctx.needs_input_grad[0]:
            raise ValueError(
                "hash-grid encoding has no gradient with respect to positions; pass x.detach() "
                "(only the table is differentiable)"
            )
        if stored is not None and (not isinstance(stored, torch.Tensor) or stored.shape != table.shape):
            raise ValueError(
                f"stored must be a copy of the table of its shape {tuple(table.shape)}, got {_describe(stored)}"
            )
        framework = backend.check_framework(framework)
        out = hashgrid_forward(x, table if stored is None else stored, resolutions, framework=framework)
        ctx.save_for_backward(x, resolutions)
        ctx.table_size = table.shape[1]
        ctx.table_dtype = table.dtype
        ctx.framework = framework
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, resolutions = ctx.saved_tensors
        grad_table = None
        if ctx.needs_input_grad[1]:
            if not _row_or_feature_major(grad_out):
                grad_out = grad_out.contiguous()
            # a feature-major gradient (the training step's, see hashgrid_backward) goes as it is: Warp reads it in
            # place, which beats a row-major copy and its read (docs/benchmarks.md, kernels.hashgrid)
            grad_table = hashgrid_backward(x, grad_out, resolutions, ctx.table_size, framework=ctx.framework)
            grad_table = grad_table.to(ctx.table_dtype)
        return None, grad_table, None, None, None


@dataclass(frozen=True)
class HashGridConfig:
    """Hyper-parameters of the encoding (instant-NGP defaults for NeRF).

    Attributes:
        levels: ``L``, number of grids.
        features: ``F``, floats per table row.
        log2_table_size: ``log2 T``, rows per level.
        base_resolution: ``N_min``, cells per unit length of the coarsest grid.
        max_resolution: ``N_max``, cells per unit length of the finest grid; scale it with the scene
            (e.g. ``2048 * scene_extent`` for an unbounded scene's box).
        init_scale: table entries start uniform in ``[-init_scale, init_scale]`` (unitless features).
        table_dtype: what the forward pass gathers from: ``"float32"``, the trained table itself, or ``"float16"``,
            a float16 copy of it (half the bytes per gathered row; each stored value rounded to within a relative
            ``2^-11``). Either way the parameter, its gradient and the optimiser's state stay float32: the float32
            table is the master copy, and :class:`HashGridEncoding` makes the float16 copy again whenever it changed.
    """

    levels: int = 16
    features: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    max_resolution: int = 2048
    init_scale: float = 1e-4
    table_dtype: str = "float32"

    def __post_init__(self):
        if self.features < 1 or not 0 <= self.log2_table_size <= 30 or self.init_scale < 0:
            raise ValueError(
                f"need features >= 1, 0 <= log2_table_size <= 30 and init_scale >= 0, got {self}"
            )
        if self.table_dtype not in TABLE_DTYPES:
            raise ValueError(
                f"table_dtype must be one of {', '.join(map(repr, TABLE_DTYPES))}, got {self.table_dtype!r}"
            )
        level_resolutions(self.levels, self.base_resolution, self.max_resolution)

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table_size

    @property
    def output_dim(self) -> int:
        return self.levels * self.features


class HashGridEncoding(torch.nn.Module):
    """Trainable hash-grid encoding: ``[N, 3]`` points in the unit cube to ``[N, L * F]`` features.

    The table is a float32 parameter ``[L, T, F]``; move the module to the backend device with ``.to()``. With
    ``config.table_dtype == "float16"`` the kernels read a float16 copy of it (:meth:`read_table`), made again
    exactly when the table changed: when the parameter's version counter moved (in-place changes through torch:
    ``copy_``, ``load_state_dict``, a for-each or single-tensor optimiser step), when its storage was replaced
    (``.to()``), or after :meth:`mark_table_changed`. Torch does not count every write: a fused optimiser step
    (``torch.optim.Adam(..., fused=True)``, the trainer's on CUDA) and writes through ``.data`` leave the version
    counter as it was, so whoever makes them announces them (:meth:`pienerf.nerf.field.NGPField.mark_weights_changed`
    does, which the trainer calls after every step).
    """

    def __init__(self, config: HashGridConfig | None = None, framework: str | None = None):
        super().__init__()
        self.config = config or HashGridConfig()
        self.framework = framework if framework is None else backend.check_framework(framework)
        c = self.config
        table = torch.empty(c.levels, c.table_size, c.features, dtype=torch.float32)
        self.table = torch.nn.Parameter(table.uniform_(-c.init_scale, c.init_scale))
        self.register_buffer("resolutions", level_resolutions(c.levels, c.base_resolution, c.max_resolution))
        self._generation = 0
        self._copy: torch.Tensor | None = None  # the float16 copy the kernels read
        self._copied_from: tuple | None = None  # (source tensor, its version, generation) the copy was made at

    @property
    def output_dim(self) -> int:
        return self.config.output_dim

    def mark_table_changed(self) -> None:
        """Announce a change of the table torch's version counter does not see (a fused optimiser step, a write
        through ``.data``): the float16 copy is made again at the next :meth:`read_table`."""
        self._generation += 1

    def read_table(self) -> torch.Tensor:
        """The table the kernels read: the parameter itself (``table_dtype = "float32"``), or its float16 copy,
        refreshed first when the parameter changed since the copy was made (class docstring). Not differentiable
        in the float16 case: gradients reach the parameter through :meth:`forward`."""
        table = self.table
        dtype = TABLE_DTYPES[self.config.table_dtype]
        if table.dtype == dtype:
            return table
        if self._copied_from is not None:
            source, version, generation = self._copied_from
            # the source is held, so its storage cannot be freed and reused by another tensor at the same address
            if (
                source.data_ptr() == table.data_ptr()
                and source.device == table.device
                and version == table._version
                and generation == self._generation
                and self._copy.shape == table.shape
            ):
                return self._copy
        with torch.no_grad():
            copy = self._copy
            if copy is None or copy.shape != table.shape or copy.device != table.device or copy.is_inference():
                copy = torch.empty(table.shape, dtype=dtype, device=table.device)
            copy.copy_(table)  # round to nearest
        self._copy = copy
        self._copied_from = (table.detach(), table._version, self._generation)
        return copy

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Features ``[N, L * F]`` of positions ``x`` ``[N, 3]`` (float32, unit cube, no gradient)."""
        stored = self.read_table()
        return HashGridFunction.apply(
            x, self.table, self.resolutions, self.framework, None if stored is self.table else stored
        )


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"{value.dtype} tensor of shape {tuple(value.shape)}"
    return type(value).__name__


def _check_table(table: torch.Tensor, what: str) -> tuple[int, int, int]:
    if not isinstance(table, torch.Tensor) or table.dtype not in TABLE_DTYPES.values():
        raise TypeError(
            f"{what} must be a float32 or float16 tensor, got {_describe(table)}; convert it with .float()"
        )
    if table.dim() != 3 or min(table.shape) < 1:
        raise ValueError(f"{what} must be [L, T, F] with L, T, F >= 1, got {tuple(table.shape)}")
    if not table.is_contiguous():
        raise ValueError(f"{what} must be contiguous [L, T, F], got strides {table.stride()}; call .contiguous()")
    if table.shape[1] > _MAX_TABLE_SIZE:
        raise ValueError(f"{what} has T = {table.shape[1]} rows per level; at most 2^31 - 1 are supported")
    return tuple(table.shape)


def _check_levels(x: torch.Tensor, resolutions: torch.Tensor, levels: int) -> torch.Tensor:
    """Validate positions and resolutions; return the resolutions as int32 on the backend device."""
    if not isinstance(x, torch.Tensor) or x.dtype != torch.float32:
        raise TypeError(f"x must be a float32 tensor, got {_describe(x)}; convert it with .float()")
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"x must be [N, 3] positions, got shape {tuple(x.shape)}")
    if not isinstance(resolutions, torch.Tensor) or resolutions.dtype not in (torch.int32, torch.int64):
        raise TypeError(
            f"resolutions must be an int32 or int64 tensor [L], got {_describe(resolutions)}; "
            "build it with level_resolutions()"
        )
    if resolutions.dim() != 1 or resolutions.shape[0] != levels or levels == 0:
        raise ValueError(
            f"resolutions must be [L] with one entry per table level (L = {levels}), got {tuple(resolutions.shape)}"
        )
    if x.shape[0] * levels > _MAX_THREADS:
        raise ValueError(f"{x.shape[0]} points x {levels} levels exceed 2^31 - 1 threads; encode the points in chunks")
    if resolutions.device.type == "cpu" and int(resolutions.min()) < 1:
        raise ValueError(f"resolutions must be >= 1 cell per unit length, got {resolutions.tolist()}")
    return resolutions.to(device=backend.torch_device(), dtype=torch.int32).contiguous()
