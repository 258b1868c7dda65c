"""Cutting a body: kernels stop influencing points across a cut, so the pieces separate (§5, Fig. 7).

A cut is a visibility criterion for the Q-GMLS shape functions: kernel i may influence point x only
if the segment from x to the kernel centre x_i does not pass through the cut. With the derivative
terms of Q-GMLS a single visible kernel keeps G(x) invertible, so every piece that holds a kernel
stays a well-posed body of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["CutMask", "CutPlane"]


@dataclass(frozen=True)
class CutPlane:
    """A planar cut: a disc of ``radius`` (m) around ``point`` in the plane with ``normal``;
    ``radius = inf`` cuts through the whole body."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float = math.inf

    def __post_init__(self):
        if not all(math.isfinite(v) for v in (*self.point, *self.normal)) or not self.radius > 0:
            raise ValueError(f"cut plane needs a finite point and normal and a radius > 0, got {self}")
        if sum(v * v for v in self.normal) == 0:
            raise ValueError("cut plane normal must be non-zero")

    def visibility(self, x: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """``[M, n]`` True where the segment x → x_i misses the cut disc."""
        point = torch.tensor(self.point, dtype=x.dtype, device=x.device)
        normal = torch.tensor(self.normal, dtype=x.dtype, device=x.device)
        normal = normal / normal.norm()
        side_x = (x - point) @ normal  # [M]
        side_c = (centres - point) @ normal  # [n]
        crosses = side_x[:, None] * side_c[None, :] < 0
        if math.isinf(self.radius):
            return ~crosses
        t = side_x[:, None] / (side_x[:, None] - side_c[None, :]).where(crosses, torch.ones_like(side_c[None, :]))
        hit = x[:, None, :] + t[..., None] * (centres[None, :, :] - x[:, None, :])
        inside = (hit - point).norm(dim=-1) < self.radius
        return ~(crosses & inside)


@dataclass(frozen=True)
class CutMask:
    """A cut given as piece labels: ``labels [P]`` of the particles at ``positions [P, 3]``.

    A point belongs to the piece of its nearest labelled particle, and a kernel influences only
    points of its own piece.
    """

    positions: torch.Tensor
    labels: torch.Tensor

    def _label(self, x: torch.Tensor) -> torch.Tensor:
        positions = self.positions.to(x)
        nearest = torch.cat([torch.cdist(chunk, positions).argmin(1) for chunk in x.split(4096)])
        return self.labels.to(x.device)[nearest]

    def visibility(self, x: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """``[M, n]`` True where point and kernel centre lie in the same piece."""
        return self._label(x)[:, None] == self._label(centres)[None, :]
