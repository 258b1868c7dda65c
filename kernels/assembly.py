"""Sparse Newton matrices from dense element Hessians.

A Newton step of an incremental potential (IPC, and PhysAvatar's garment solver) sums per-element Hessians
``H_e`` (``3k × 3k`` for an element of ``k`` vertices) into one sparse matrix over the free vertices. Vertices are
free (an unknown of the solve) or kinematic (a prescribed displacement ``p_j``): a block ``H_ij`` between a free
``i`` and a kinematic ``j`` moves to the right-hand side as ``−H_ij p_j``.

:func:`scatter_hessians` does it in one Warp kernel launch per element kind: a thread takes one element and adds
each of its 3×3 blocks atomically to the values of a fixed block pattern (:class:`BlockPattern`, found by a binary
search of the block row), or pushes it to the right-hand side. This replaces the COO indexing, sorting and summing
of an assembly in torch (about 40 tensor operations per matrix, each a launch on a GPU).

A block ``B = H_ij`` that the pattern lacks is counted and bounded instead of written: ``‖B‖_F I`` goes to the
diagonal block of row ``i`` (and, from ``H_ji``, to that of ``j``). Since ``[[sI, −B], [−Bᵀ, sI]] ⪰ 0`` for
``s ≥ ‖B‖₂``, the matrix assembled is the exact one plus a PSD matrix: it stays SPD where the exact one is, and its
Newton direction is still a descent direction, only a shorter one along the missing couplings. The caller may use
it as it is and grow the pattern later (a pattern change costs a sparse direct solver a new analysis), or grow the
pattern now and assemble again.

The values array holds every stored entry of both triangles in scalar CSR order (``crow``/``col`` of the pattern),
which is what cuDSS, SciPy and ``torch.sparse_csr_tensor`` take.

PSD filtering stays with the caller (:func:`kernels.element_terms.project_psd`, a batched eigen-decomposition). A
thread-per-element cyclic Jacobi filter inside this kernel was measured and dropped: its rotations form one long
dependent chain per thread, through memory, slower than cuSOLVER's batched eigensolvers on CUDA and than LAPACK on
the CPU (``docs/benchmarks.md``).
"""

from typing import NamedTuple

import torch
import warp as wp

from kernels import backend, cudss

wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["BlockPattern", "block_keys", "block_pattern", "scatter_hessians"]


class BlockPattern(NamedTuple):
    """Sparsity pattern of an ``n × n`` block matrix of 3×3 blocks, with the scalar CSR structure of its values.

    Attributes:
        n: block rows (free vertices).
        block_start: ``[n + 1]`` int32 offsets of each block row in ``block_col``.
        block_col: ``[K]`` int32 block columns, sorted within each row.
        crow: ``[3n + 1]`` int32 scalar CSR row offsets (every entry of both triangles).
        col: ``[9K]`` int32 scalar CSR column indices.
        diagonal: ``[n, 3, 3]`` int64 positions of the diagonal blocks' entries in the values array.
    """

    n: int
    block_start: torch.Tensor
    block_col: torch.Tensor
    crow: torch.Tensor
    col: torch.Tensor
    diagonal: torch.Tensor

    def keys(self) -> torch.Tensor:
        """``[K]`` int64 keys ``row · n + col`` of the blocks, sorted (what :func:`block_pattern` takes)."""
        counts = (self.block_start[1:] - self.block_start[:-1]).long()
        rows = torch.repeat_interleave(torch.arange(self.n, device=counts.device), counts)
        return rows * self.n + self.block_col.long()


def block_keys(index: torch.Tensor, dof: torch.Tensor, n: int) -> torch.Tensor:
    """The blocks that elements over ``index [N, k]`` add between free vertices, as keys ``row · n + col``.

    Args:
        index: ``[N, k]`` vertex indices.
        dof: ``[V]`` block row of each vertex, ``-1`` for a kinematic one.
        n: free vertices.

    Returns:
        ``[M]`` int64 keys, with repeats.
    """
    d = dof.long()[index.long()]
    k = index.shape[1]
    rows = d[:, :, None].expand(-1, k, k).reshape(-1)
    cols = d[:, None, :].expand(-1, k, k).reshape(-1)
    both = (rows >= 0) & (cols >= 0)
    return (rows * n + cols)[both]


def block_pattern(keys: torch.Tensor, n: int) -> BlockPattern:
    """The pattern of the blocks ``keys`` (``row · n + col``, repeats allowed) and of every diagonal block.

    Raises:
        ValueError: a key outside ``[0, n²)``.
    """
    device = keys.device
    diagonal_keys = torch.arange(n, device=device, dtype=torch.int64) * (n + 1)
    keys = torch.unique(torch.cat([keys.to(torch.int64), diagonal_keys]))
    if keys.numel() and (int(keys[0]) < 0 or int(keys[-1]) >= n * n):
        raise ValueError(f"block keys must lie in [0, {n * n}) for {n} block rows")
    rows, cols = keys // n, keys % n
    crow, col, position = cudss.block_pattern_csr(rows, cols, n)  # the scalar layout the kernel writes into
    start = torch.zeros(n + 1, dtype=torch.int64, device=device)
    start[1:] = torch.cumsum(torch.bincount(rows, minlength=n), 0)
    diagonal = position[rows == cols]  # blocks (i, i) in order of i
    return BlockPattern(
        n,
        start.to(torch.int32),
        cols.to(torch.int32),
        crow.to(torch.int32),
        col.to(torch.int32),
        diagonal,
    )


@wp.func
def _find_block(block_start: wp.array(dtype=wp.int32), block_col: wp.array(dtype=wp.int32), row: int, col: int):
    """Index of block ``(row, col)`` in ``block_col``, or -1."""
    lo = block_start[row]
    hi = block_start[row + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        c = block_col[mid]
        if c == col:
            return mid
        if c < col:
            lo = mid + 1
        else:
            hi = mid
    return -1


@wp.kernel
def _scatter_kernel(
    index: wp.array2d(dtype=wp.int32),
    hess: wp.array3d(dtype=wp.float64),
    scale: wp.float64,
    dof: wp.array(dtype=wp.int32),
    p_kin: wp.array(dtype=wp.vec3d),
    block_start: wp.array(dtype=wp.int32),
    block_col: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.float64),
    rhs: wp.array(dtype=wp.vec3d),
    missing: wp.array(dtype=wp.int32),
):
    e = wp.tid()
    k = index.shape[1]
    for vi in range(k):
        row = dof[index[e, vi]]
        if row >= 0:
            for vj in range(k):
                vertex = index[e, vj]
                col = dof[vertex]
                block = wp.mat33d()
                for x in range(3):
                    for y in range(3):
                        block[x, y] = scale * hess[e, 3 * vi + x, 3 * vj + y]
                if col < 0:
                    wp.atomic_sub(rhs, row, block * p_kin[vertex])
                else:
                    at = _find_block(block_start, block_col, row, col)
                    if at < 0:  # bounded by its norm on the diagonal (row == col is always in the pattern)
                        wp.atomic_add(missing, 0, 1)
                        block = wp.identity(n=3, dtype=wp.float64) * wp.sqrt(wp.ddot(block, block))
                        at = _find_block(block_start, block_col, row, row)
                    # block row ``row`` holds scalar rows 3 row + x, each 3 · (its block count) long
                    first = block_start[row]
                    origin = 9 * first + 3 * (at - first)
                    length = 3 * (block_start[row + 1] - first)
                    for x in range(3):
                        for y in range(3):
                            wp.atomic_add(values, origin + x * length + y, block[x, y])


def scatter_hessians(
    pattern: BlockPattern,
    values: torch.Tensor,
    rhs: torch.Tensor,
    missing: torch.Tensor,
    index: torch.Tensor,
    hess: torch.Tensor,
    dof: torch.Tensor,
    p_kin: torch.Tensor,
    scale: float = 1.0,
) -> None:
    """Add ``scale`` times the element Hessians into a block-sparse matrix and its right-hand side.

    Args:
        pattern: the matrix's :class:`BlockPattern` over ``n`` free vertices.
        values: ``[9K]`` float64 values in ``pattern``'s scalar CSR order; accumulated into.
        rhs: ``[n, 3]`` float64 right-hand side; receives ``−scale H_ij p_j`` for free ``i``, kinematic ``j``.
        missing: ``[1]`` int32; counts the free–free blocks that ``pattern`` lacks (each is bounded by its
            Frobenius norm on its row's diagonal instead of added: see the module's notes).
        index: ``[N, k]`` int32 vertex indices of the elements.
        hess: ``[N, 3k, 3k]`` float64 element Hessians, vertex-major (``3 · vertex + axis``).
        dof: ``[V]`` int32 block row of each vertex, ``-1`` for a kinematic one.
        p_kin: ``[V, 3]`` float64 displacement of each kinematic vertex (read where ``dof`` is ``-1``).
        scale: factor on every Hessian (e.g. ``Δt²``).

    Raises:
        ValueError: mismatched shapes or dtypes.
    """
    count, k = index.shape if index.dim() == 2 else (-1, -1)
    if count < 0 or tuple(hess.shape) != (count, 3 * k, 3 * k):
        raise ValueError(f"index must be [N, k] and hess [N, 3k, 3k], got {tuple(index.shape)} {tuple(hess.shape)}")
    if index.dtype != torch.int32 or dof.dtype != torch.int32:
        raise ValueError(f"index and dof must be int32, got {index.dtype} and {dof.dtype}")
    for name, t in (("hess", hess), ("values", values), ("rhs", rhs), ("p_kin", p_kin)):
        if t.dtype != torch.float64:
            raise ValueError(f"{name} must be float64, got {t.dtype}")
    if tuple(rhs.shape) != (pattern.n, 3) or values.numel() != pattern.col.numel():
        raise ValueError(
            f"rhs must be [{pattern.n}, 3] and values hold {pattern.col.numel()} entries, got "
            f"{tuple(rhs.shape)} and {values.numel()}"
        )
    if tuple(p_kin.shape) != (dof.numel(), 3):
        raise ValueError(f"p_kin must be [{dof.numel()}, 3] (one row per vertex), got {tuple(p_kin.shape)}")
    if count == 0:
        return
    backend.launch(
        _scatter_kernel,
        count,
        [
            index.contiguous(),
            hess.contiguous(),
            float(scale),
            dof,
            (p_kin.contiguous(), wp.vec3d),
            pattern.block_start,
            pattern.block_col,
            values,
            (rhs, wp.vec3d),
            missing,
        ],
    )
