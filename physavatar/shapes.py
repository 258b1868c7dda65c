"""Simple cloth and collider meshes: regular sheets and spheres (test scenes, benchmarks, Fig. 9)."""

from __future__ import annotations

import torch
import trimesh

__all__ = ["grid_sheet", "icosphere"]


def grid_sheet(nx: int, ny: int, spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A regular sheet of ``nx × ny`` vertices in the xy plane from the origin.

    Every square cell (i, j) is split by the same diagonal, from vertex (i + 1, j) to (i, j + 1); the
    discrete-shell bending constant of such a mesh depends on that choice.

    Returns:
        ``vertices [nx·ny, 3]`` float64 (m) with index ``i·ny + j`` at ``(i·spacing, j·spacing, 0)``,
        and ``faces [2(nx−1)(ny−1), 3]`` int32, counter-clockwise seen from +z.
    """
    i, j = torch.meshgrid(torch.arange(nx), torch.arange(ny), indexing="ij")
    zeros = torch.zeros(nx * ny, dtype=torch.float64)
    vertices = torch.stack([spacing * i.reshape(-1).double(), spacing * j.reshape(-1).double(), zeros], 1)
    v = (i * ny + j)[:-1, :-1].reshape(-1)
    faces = torch.cat([torch.stack([v, v + ny, v + 1], 1), torch.stack([v + 1, v + ny, v + ny + 1], 1)])
    return vertices, faces.to(torch.int32)


def icosphere(level: int, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Outward-oriented icosphere about the origin, subdivided ``level`` times (10·4^level + 2 vertices).

    Returns:
        ``vertices [V, 3]`` float64 (m) and ``faces [F, 3]`` int32.
    """
    mesh = trimesh.creation.icosphere(subdivisions=level, radius=radius)
    return torch.tensor(mesh.vertices, dtype=torch.float64), torch.tensor(mesh.faces, dtype=torch.int32)
