"""How far a warped-NeRF render lies from the mesh render of the same simulated state, on one region of the body.

PIE-NeRF's Fig. 8 bends a rod stuck in a teapot and shows that quadratic ray warping (Eq. 20) fetches the rod's colour
where linear warping leaves artifacts. :class:`WarpErrorProbe` puts a number on it, per warping. Each measured frame
it renders, with no ground (the ground differs between the mesh and the NeRF renderers and would fill the
silhouettes):

* the reference: the scene's mesh carried by the Q-GMLS field (Eq. 9), its edges split so that the bend shows
  (:class:`pienerf.render.previews.MeshRenderBackend` with ``max_edge``);
* the NeRF warped by each warping (:class:`pienerf.render.previews.NerfRenderBackend`), from the same state q.

The region is where the chosen material is now: the body's particles whose rest positions lie in a box (the rod),
moved to their deformed positions, projected, and drawn as discs of the particle radius r̄ widened by ``dilation``
pixels (:func:`region_mask`). The region follows the bend; what lies inside it and is covered by either render
(alpha > ½, the silhouette) is measured (:func:`region_error`):

* ``psnr_db``: PSNR of the colours composited over white, on the pixels that either silhouette covers;
* ``silhouette_iou``: |mesh ∩ NeRF| / |mesh ∪ NeRF| of the silhouettes inside the region;
* ``pixels``: how many pixels the union holds (0: nothing to measure, both metrics ``None``).

Sums run over every view, so a frame seen by several cameras gets one number per warping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kernels.image_metrics import psnr
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.field import OccupancyGrid
from pienerf.render.previews import MeshRenderBackend, NerfRenderBackend
from pienerf.sim.model import QGMLSModel

__all__ = ["SILHOUETTE_ALPHA", "RegionError", "WarpErrorProbe", "region_error", "region_mask"]

SILHOUETTE_ALPHA = 0.5
"""A pixel belongs to a render's silhouette where its alpha exceeds this."""


@dataclass(frozen=True)
class RegionError:
    """One warped render against its reference on a region (module docstring).

    Attributes:
        psnr_db: PSNR of the colours over white on the silhouettes' union (dB), ``inf`` where they agree exactly,
            ``None`` where the union is empty.
        silhouette_iou: intersection over union of the silhouettes in [0, 1], ``None`` where the union is empty.
        pixels: pixels in the union.
    """

    psnr_db: float | None
    silhouette_iou: float | None
    pixels: int

    def to_dict(self) -> dict:
        return {"psnr_db": self.psnr_db, "silhouette_iou": self.silhouette_iou, "pixels": self.pixels}


def region_mask(
    points: torch.Tensor, radius: torch.Tensor, cameras: Cameras, view: int, dilation: float = 2.0
) -> torch.Tensor:
    """``[H, W]`` bool: pixels whose centre lies within a point's projected disc, widened by ``dilation`` pixels.

    Args:
        points: ``[R, 3]`` world positions (m).
        radius: ``[R]`` radius of each point's disc (m), projected at the point's depth.
        cameras: the cameras; ``view`` picks one.
        dilation: pixels added to every projected radius, ≥ 0.
    """
    if not (math.isfinite(dilation) and dilation >= 0):
        raise ValueError(f"dilation must be a finite number of pixels >= 0, got {dilation!r}")
    cameras = cameras.to("cpu")
    points = points.detach().double().cpu()
    u, v, depth = cameras.project(view, points)
    front = depth > 1e-6
    reach = float(cameras.fx[view]) * radius.detach().double().cpu() / depth.clamp_min(1e-6) + dilation
    u, v, reach = u[front], v[front], reach[front]
    mask = torch.zeros(cameras.height * cameras.width, dtype=torch.bool)
    rows, cols = torch.meshgrid(
        torch.arange(cameras.height, dtype=torch.float64) + 0.5,
        torch.arange(cameras.width, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    centres = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=1)
    discs = torch.stack([u, v], dim=1)
    for start in range(0, len(discs), 64):  # [H·W, 64] distances at a time
        chunk = slice(start, start + 64)
        mask |= (torch.cdist(centres, discs[chunk]) <= reach[chunk]).any(dim=1)
    return mask.reshape(cameras.height, cameras.width)


def region_error(reference: torch.Tensor, rendered: torch.Tensor, mask: torch.Tensor) -> RegionError:
    """Compare two straight-alpha RGBA images ``[H, W, 4]`` on ``mask [H, W]`` (module docstring)."""
    return _Tally().add(reference, rendered, mask).result()


class _Tally:
    """What :func:`region_error` compares, gathered over several views: the union's colours and the silhouettes'
    intersection and union counts."""

    def __init__(self):
        self.reference, self.rendered, self.intersection, self.union = [], [], 0, 0

    def add(self, reference: torch.Tensor, rendered: torch.Tensor, mask: torch.Tensor) -> _Tally:
        if reference.shape != rendered.shape or reference.shape[:2] != mask.shape or reference.shape[-1] != 4:
            raise ValueError(
                f"images must be [H, W, 4] of one size with a [H, W] mask, got {tuple(reference.shape)}, "
                f"{tuple(rendered.shape)} and {tuple(mask.shape)}"
            )
        reference, rendered, mask = reference.cpu().double(), rendered.cpu().double(), mask.cpu()
        mine, theirs = reference[..., 3] > SILHOUETTE_ALPHA, rendered[..., 3] > SILHOUETTE_ALPHA
        union = (mine | theirs) & mask
        self.intersection += int((mine & theirs & mask).sum())
        self.union += int(union.sum())
        for image, gathered in ((reference, self.reference), (rendered, self.rendered)):
            over_white = image[..., :3] * image[..., 3:] + (1.0 - image[..., 3:])
            gathered.append(over_white.clamp(0.0, 1.0)[union])
        return self

    def result(self) -> RegionError:
        if self.union == 0:
            return RegionError(None, None, 0)
        error = psnr(torch.cat(self.rendered), torch.cat(self.reference))
        return RegionError(float(error), self.intersection / self.union, self.union)


class WarpErrorProbe:
    """Renders a body by its mesh and by each warping of its NeRF, with no ground, and measures each NeRF render
    against the mesh on a region of material (module docstring).

    Args:
        model: the discretised body; its particles inside ``region`` are the measured material.
        mesh: ``(vertices [V, 3] m, faces [F, 3], colors [V, 3])`` of the body at rest, e.g.
            :meth:`pienerf.render.previews.MeshRenderBackend.body_mesh` of the refined preview.
        field, grid: the rest-space NeRF and its occupancy grid.
        warps: the render modes to measure and their warping, e.g. ``{"nerf": "quadratic", "nerf_linear": "linear"}``.
        region: ``(lo [3], hi [3])`` box in rest space (m) of the measured material.
        dilation: pixels added to the projected particle radius (:func:`region_mask`).
        max_edge: split the mesh's edges down to this length first (m), ``None`` to take it as given.
        label: what the region holds (e.g. ``"rod"``), for reports.

    Raises:
        ValueError: no particle rests in ``region``, or a box with ``lo > hi``.
    """

    def __init__(
        self,
        model: QGMLSModel,
        mesh: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        field,
        grid: OccupancyGrid,
        warps: dict[str, str],
        region: tuple,
        dilation: float = 2.0,
        max_edge: float | None = None,
        label: str = "region",
    ):
        lo, hi = (torch.as_tensor(c, dtype=torch.float64, device=model.device).reshape(3) for c in region)
        if bool((lo > hi).any()):
            raise ValueError(f"region box must be (lo, hi) with lo <= hi on every axis, got {region!r}")
        inside = ((model.position >= lo) & (model.position <= hi)).all(dim=1)
        if not bool(inside.any()):
            raise ValueError(
                f"no particle of the body rests in the region box {lo.tolist()} to {hi.tolist()} (m); "
                "widen the box or move it onto the body"
            )
        self.model = model
        self.region, self.label = (lo.tolist(), hi.tolist()), label
        self.index = torch.nonzero(inside)[:, 0]
        self.radius = (3.0 * model.volume[self.index] / (4.0 * math.pi)).pow(1.0 / 3.0)
        self.dilation = float(dilation)
        self.mesh = MeshRenderBackend(model, *mesh, ground_height=None, max_edge=max_edge)
        self.nerfs = {
            name: NerfRenderBackend(field, grid, model, mode=warp, ground=None) for name, warp in warps.items()
        }

    @property
    def particle_count(self) -> int:
        """Particles of the measured material."""
        return len(self.index)

    def measure(self, q: torch.Tensor, cameras: Cameras) -> dict[str, RegionError]:
        """Every warping's :class:`RegionError` at state ``q [nT, 3]``, summed over the views of ``cameras``."""
        points = self.model.particles.positions(q)[self.index]
        tallies = {name: _Tally() for name in self.nerfs}
        for view in range(len(cameras)):
            mask = region_mask(points, self.radius, cameras, view, self.dilation)
            reference = self.mesh.render(q, cameras, view).rgba
            for name, nerf in self.nerfs.items():
                tallies[name].add(reference, nerf.render(q, cameras, view).rgba, mask)
        return {name: tally.result() for name, tally in tallies.items()}
