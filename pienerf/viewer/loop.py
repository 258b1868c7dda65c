"""The pieces of the interactive demo's loop that every front end shares: render modes, load-on-demand NeRF and the
refinement schedule of server-rendered previews."""

from __future__ import annotations

import torch

from pienerf.nerf_backend import NerfFit, scene_nerf
from pienerf.scenes import SCENES
from pienerf.train import load_checkpoint

__all__ = ["RENDER_MODES", "RefinementSchedule", "load_nerf"]

RENDER_MODES = ("mesh", "particles", "nerf")
"""What the viewer can show: the browser's mesh, the browser's particles, or the server's warped-NeRF image."""


def load_nerf(simulation, checkpoint: str | None = None, fit=None, cache_dir: str | None = None, progress=None):
    """Give ``simulation`` its ``"nerf"`` render mode: a given checkpoint, else the NeRF of its embedded scene
    (trained on the scene's rendered views, or loaded from the cache); returns the render backend."""
    if "nerf" in simulation.render_backends:
        return simulation.render_backends["nerf"]
    if checkpoint is not None:
        trained = load_checkpoint(checkpoint)
    elif simulation.config.scene in SCENES:
        trained = scene_nerf(simulation.config.scene, fit or NerfFit(), cache_dir, progress)
    else:
        raise ValueError(
            f"no NeRF for the mesh scene {simulation.config.scene!r}: pass --nerf-checkpoint PATH "
            "(trained in the mesh's coordinates) or use an embedded scene"
        )
    return simulation.add_nerf_render(trained.field, trained.grid)


class RefinementSchedule:
    """The resolution a preview is rendered at: coarse while the body or the camera moves, full once still.

    Args:
        moving: downscale while things move.
        still: downscale of the refined image.
        tolerance: generalized coordinates that changed less than this (m) since the last render count as still.
    """

    def __init__(self, moving: int = 4, still: int = 1, tolerance: float = 1e-4):
        self.moving, self.still, self.tolerance = moving, still, tolerance
        self._q: torch.Tensor | None = None
        self._camera = None
        self._level: int | None = None

    def next(self, q: torch.Tensor, camera) -> int | None:
        """The downscale to render at now, or ``None`` when the shown image is already the refined one.

        Args:
            q: ``[nT, 3]`` the body's state.
            camera: any comparable description of the view (changes when the camera moves).
        """
        moved = (
            self._q is None
            or self._q.shape != q.shape
            or camera != self._camera
            or float((q - self._q).abs().max()) > self.tolerance
        )
        if moved:
            self._q, self._camera, self._level = q.detach().clone(), camera, self.moving
            return self.moving
        if self._level != self.still:
            self._level = self.still
            return self.still
        return None
