"""Reference of :mod:`kernels.hashgrid` in plain torch, vectorised over points (a loop over levels only).

The forward pass is differentiable with respect to the table through torch's autograd (``gather``);
:func:`hashgrid_backward_torch` writes the same gradient explicitly as a scatter-add.
"""

from __future__ import annotations

import torch

from kernels.hashgrid import HASH_PRIMES

__all__ = ["cell_corners_torch", "hashgrid_backward_torch", "hashgrid_forward_torch", "spatial_hash_torch"]

# Corner c of a cell has offset bit a along axis a, as in the kernels.
_CORNER_OFFSETS = torch.tensor([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=torch.int64)


def spatial_hash_torch(vertices: torch.Tensor, table_size: int) -> torch.Tensor:
    """Eq. 4 of Müller et al. 2022: ``(v_x * 1 XOR v_y * pi_2 XOR v_z * pi_3) mod T`` in uint32 arithmetic.

    Args:
        vertices: int64 ``[..., 3]`` grid vertices (non-negative).
        table_size: ``T``.

    Returns:
        int64 ``[...]`` table rows in ``[0, T)``.
    """
    # The products fit in int64; their low 32 bits are the uint32 products, and XOR works bit by bit.
    h = vertices[..., 0] * HASH_PRIMES[0]
    h = h ^ (vertices[..., 1] * HASH_PRIMES[1])
    h = h ^ (vertices[..., 2] * HASH_PRIMES[2])
    return (h & 0xFFFFFFFF) % table_size


def cell_corners_torch(x: torch.Tensor, resolution: int, table_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Table rows and trilinear weights of the 8 cell corners around each point on one level.

    Points are clamped to ``[0, 1]^3``; the cell is ``floor(x N)`` clamped to ``[0, N - 1]``. Rows are
    dense (``x + (N+1) (y + (N+1) z)``) when ``(N + 1)^3 <= T``, else hashed (Eq. 4).

    Args:
        x: float32 ``[N, 3]`` positions.
        resolution: ``N_l`` of the level.
        table_size: ``T``.

    Returns:
        int64 rows ``[N, 8]`` and float32 weights ``[N, 8]`` (each row of weights sums to 1).
    """
    p = x.clamp(0.0, 1.0) * float(resolution)
    cell = p.floor().clamp(0, resolution - 1)
    local = p - cell
    offsets = _CORNER_OFFSETS.to(x.device)
    vertices = cell.long()[:, None, :] + offsets[None]  # [N, 8, 3]
    side = resolution + 1
    if side**3 <= table_size:
        rows = vertices[..., 0] + side * (vertices[..., 1] + side * vertices[..., 2])
    else:
        rows = spatial_hash_torch(vertices, table_size)
    factors = torch.where(offsets[None].bool(), local[:, None, :], 1.0 - local[:, None, :])  # [N, 8, 3]
    return rows, factors.prod(dim=-1)


def hashgrid_forward_torch(x: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor) -> torch.Tensor:
    """Reference of :func:`kernels.hashgrid.hashgrid_forward`: ``[N, 3]`` points, ``[L, T, F]`` table, ``[N, L F]``."""
    levels, table_size, features = table.shape
    out = []
    for level, resolution in enumerate(resolutions.tolist()):
        rows, weights = cell_corners_torch(x, resolution, table_size)
        corner_features = table[level][rows]  # [N, 8, F]
        out.append((weights[..., None] * corner_features).sum(dim=1))
    return torch.cat(out, dim=1)


def hashgrid_backward_torch(
    x: torch.Tensor, grad_out: torch.Tensor, resolutions: torch.Tensor, table_size: int
) -> torch.Tensor:
    """Reference of :func:`kernels.hashgrid.hashgrid_backward`: scatter-add ``[N, L * F]`` into ``[L, T, F]``."""
    levels = resolutions.shape[0]
    features = grad_out.shape[1] // levels
    grad_table = torch.zeros(levels, table_size, features, dtype=grad_out.dtype, device=grad_out.device)
    for level, resolution in enumerate(resolutions.tolist()):
        rows, weights = cell_corners_torch(x, resolution, table_size)
        g = grad_out[:, level * features : (level + 1) * features]
        contributions = weights[..., None] * g[:, None, :]  # [N, 8, F]
        grad_table[level].index_add_(0, rows.reshape(-1), contributions.reshape(-1, features))
    return grad_table
