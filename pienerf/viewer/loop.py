"""The simulation loop behind an interactive viewer: viewer events become commands run between steps.

A front end (:class:`pienerf.viewer.viser_viewer.ViserViewer`, :class:`pienerf.viewer.meshcat_viewer.MeshcatViewer`)
implements :class:`Viewer` and only translates events: it queues commands with :meth:`DemoApp.submit`, which the
loop runs between steps through the :class:`pienerf.session.Simulation` verbs. A command that fails (a malformed
message, a bad value) is reported to the viewer and the loop goes on.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from kernels.hashgrid import HashGridConfig
from pienerf.nerf import NGPConfig
from pienerf.nerf_fit import NerfFit, scene_nerf
from pienerf.preview import RenderBackend
from pienerf.scenes import SCENES
from pienerf.session import Simulation
from pienerf.train import TrainConfig, load_checkpoint

__all__ = ["RENDER_MODES", "DemoApp", "Viewer", "load_nerf", "smoke_fit", "vector3"]

RENDER_MODES = ("mesh", "particles", "nerf")
"""What the viewer can show: the browser's mesh, the browser's particles, or the server's warped-NeRF image."""


def vector3(value, what: str) -> np.ndarray:
    """A finite 3-vector from a client message, or a ValueError naming the field."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} is not a 3-vector: {value!r}") from None
    if array.shape != (3,) or not np.isfinite(array).all():
        raise ValueError(f"{what} must be 3 finite numbers, got {value!r}")
    return array


def smoke_fit() -> NerfFit:
    """A NeRF fit of a few seconds for smoke runs (16 views of 32², 60 steps, a small hash grid)."""
    ngp = NGPConfig(
        hashgrid=HashGridConfig(levels=6, features=2, log2_table_size=12, base_resolution=8, max_resolution=64),
        density_hidden=16,
        color_hidden=16,
        color_layers=1,
        grid_resolution=32,
        samples_per_diagonal=128,
    )
    return NerfFit(ngp=ngp, train=TrainConfig(steps=60, batch_rays=512, grid_warmup_steps=16), views=16, resolution=32)


def load_nerf(
    simulation: Simulation, checkpoint: str | None = None, fit=None, cache_dir: str | None = None, progress=None
) -> RenderBackend:
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


class Viewer(Protocol):
    """What the demo loop needs from a display."""

    def attach(self, app: DemoApp) -> None: ...

    def update(self, app: DemoApp) -> None: ...

    def report(self, message: str) -> None: ...

    def close(self) -> None: ...


class DemoApp:
    """The simulation loop behind a viewer: runs queued commands, steps, and hands frames to the viewer.

    Args:
        simulation: the :class:`pienerf.session.Simulation`.
        viewer: the display.
        render_mode: one of :data:`RENDER_MODES`, shown first.
        nerf_options: keyword arguments of :func:`load_nerf` (``checkpoint``, ``fit``, ``cache_dir``) used when the
            NeRF mode is switched on later.
    """

    def __init__(self, simulation, viewer: Viewer, render_mode: str = "mesh", nerf_options: dict | None = None):
        if render_mode not in RENDER_MODES:
            raise ValueError(f"unknown render mode {render_mode!r}; valid: {', '.join(RENDER_MODES)}")
        self.simulation = simulation
        self.viewer = viewer
        self.render_mode = render_mode
        self.nerf_options = dict(nerf_options or {})
        self.commands: queue.Queue[tuple[str, Callable[[], object]]] = queue.Queue()
        self.stop = threading.Event()
        self.paused = False
        self.fps = 0.0
        self.errors: list[str] = []
        viewer.attach(self)

    def submit(self, what: str, command: Callable[[], object]) -> None:
        """Queue ``command`` to run in the loop thread between steps."""
        self.commands.put((what, command))

    def run_commands(self) -> None:
        while True:
            try:
                what, command = self.commands.get_nowait()
            except queue.Empty:
                return
            try:
                command()
            except Exception as error:  # a bad request must not stop the loop
                message = f"{what} failed: {error}"
                self.errors.append(message)
                self.viewer.report(message)

    def click(self, ray_origin, ray_direction) -> None:
        """A click: pick when nothing is picked, else move the drag target onto this ray at the picked depth."""
        origin = vector3(ray_origin, "click ray origin")
        direction = vector3(ray_direction, "click ray direction")
        if self.simulation.dragging:
            self.simulation.drag_to(origin, direction)
        else:
            hit = self.simulation.pick(origin, direction)
            self.viewer.report("picked nothing" if hit is None else f"picked {np.round(hit.rest.numpy(), 3)}")

    def tick(self) -> None:
        """One frame: commands, one step unless paused, display."""
        self.run_commands()
        start = time.perf_counter()
        if not self.paused:
            self.simulation.step()
        self.viewer.update(self)
        elapsed = time.perf_counter() - start
        self.fps = 0.9 * self.fps + 0.1 / max(elapsed, 1e-6) if self.fps else 1.0 / max(elapsed, 1e-6)

    def run(self, steps: int | None = None, frame_seconds: float = 1.0 / 30.0) -> None:
        """Loop until :attr:`stop` is set (or ``steps`` frames ran), at most one frame per ``frame_seconds``."""
        count = 0
        while not self.stop.is_set() and (steps is None or count < steps):
            start = time.perf_counter()
            self.tick()
            count += 1
            if steps is None:
                self.stop.wait(max(0.0, frame_seconds - (time.perf_counter() - start)))

