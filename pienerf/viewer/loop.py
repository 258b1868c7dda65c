"""The simulation loop behind an interactive viewer: viewer events become commands run between steps.

A front end (:class:`pienerf.viewer.viser_viewer.ViserViewer`, :class:`pienerf.viewer.meshcat_viewer.MeshcatViewer`)
implements :class:`Viewer` and only translates events: it queues commands with :meth:`DemoApp.submit`, which the
loop runs between steps through the :class:`pienerf.session.Simulation` verbs. A command that fails (a malformed
message, a bad value) is reported to the viewer and the loop goes on.
"""

from __future__ import annotations

import multiprocessing
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Protocol

import numpy as np

from kernels import backend
from kernels.hashgrid import HashGridConfig
from pienerf.nerf.field import NGPConfig
from pienerf.nerf.fitting import NerfFit
from pienerf.nerf.training import TrainConfig, load_checkpoint
from pienerf.render.previews import Frame, RenderBackend
from pienerf.render.refinement import RefinementSchedule
from pienerf.scenes import SCENES, scene_nerf
from pienerf.session import Simulation

__all__ = [
    "CONTROL_RANGES",
    "MAX_PENDING_COMMANDS",
    "RENDER_MODES",
    "REST_FRAMES",
    "REST_SPEED",
    "CommandQueue",
    "DemoApp",
    "NerfJob",
    "NerfSchedules",
    "Viewer",
    "control_value",
    "load_nerf",
    "render_nerf_in_budget",
    "si_text",
    "smoke_fit",
    "vector3",
]

RENDER_MODES = ("mesh", "particles", "nerf")
"""What the viewer can show: the browser's mesh, the browser's particles, or the server's warped-NeRF image."""


CONTROL_RANGES = {
    "young_modulus": (1.0e2, 1.0e9),
    "poisson_ratio": (0.0, 0.49),
    "density": (10.0, 2.0e4),
    "damping": (0.0, 100.0),
    "gravity": (0.0, 100.0),
    "kernel_count": (4, 4096),
}
"""Values a page may set, name -> (lowest, highest): Young's modulus (Pa), Poisson ratio, density (kg/m³),
Rayleigh damping α (1/s), gravity's magnitude along -y (m/s²) and the kernel count of a re-sampling."""


MAX_PENDING_COMMANDS = 256
"""Commands a viewer may have waiting for the loop; one more is refused (the page is told) until the loop catches up."""

REST_SPEED = 1.0e-3
"""Particle speed (m/s) under which the body counts as still."""

REST_FRAMES = 30
"""Consecutive still frames (1 s at 30 frames/s) after which the loop sleeps until the next event."""


_SLEEP_CHECK_SECONDS = 0.5  # a sleeping loop looks at stop (set without wake by a caller) this often


class CommandQueue:
    """The commands waiting for the simulation loop: bounded, and merged where a later one supersedes an earlier one.

    A command submitted with a ``key`` replaces the waiting command of that key (the latest drag target, the latest
    value of a slider, one reset) and moves to the back, so it still runs after what was submitted before it. A
    ``heavy`` command (a re-sampling or a cut, which rebuild the body) runs at most once a frame. Thread-safe: the
    viewers' server threads submit while the loop thread takes.

    Args:
        limit: most commands waiting at once; a further one raises ValueError.
    """

    def __init__(self, limit: int = MAX_PENDING_COMMANDS):
        self.limit = int(limit)
        self._waiting: OrderedDict[object, tuple[str, Callable[[], object], bool]] = OrderedDict()
        self._count = 0
        self._lock = threading.Lock()

    def put(self, what: str, command: Callable[[], object], key: str | None = None, heavy: bool = False) -> None:
        """Queue ``command`` (described by ``what``); see the class for ``key`` and ``heavy``."""
        with self._lock:
            if key is not None and key in self._waiting:
                self._waiting[key] = (what, command, heavy)
                self._waiting.move_to_end(key)
                return
            if len(self._waiting) >= self.limit:
                raise ValueError(
                    f"{what} refused: {self.limit} commands are already waiting for the simulation; "
                    "send fewer, it catches up within a few frames"
                )
            self._count += 1
            self._waiting[key if key is not None else self._count] = (what, command, heavy)

    def take(self) -> list[tuple[str, Callable[[], object]]]:
        """The commands of one frame, in order: everything waiting up to the second heavy one (which stays)."""
        taken, heavy_taken = [], False
        with self._lock:
            while self._waiting:
                key, (what, command, heavy) = next(iter(self._waiting.items()))
                if heavy and heavy_taken:
                    break
                heavy_taken |= heavy
                del self._waiting[key]
                taken.append((what, command))
        return taken

    def empty(self) -> bool:
        with self._lock:
            return not self._waiting

    def __len__(self) -> int:
        with self._lock:
            return len(self._waiting)


def control_value(name: str, value) -> float:
    """``value`` of the control ``name`` (:data:`CONTROL_RANGES`) as a float, or a ValueError naming the range."""
    lo, hi = CONTROL_RANGES[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"{name.replace('_', ' ')} must be a number in [{lo:g}, {hi:g}], got {str(value)[:80]}")
    return float(value)


def si_text(value: float, unit: str) -> str:
    """A value for people to read: ``20000, "Pa"`` -> ``"20 kPa"``."""
    for factor, prefix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= factor:
            return f"{value / factor:.3g} {prefix}{unit}"
    return f"{value:.3g} {unit}"


class NerfSchedules:
    """The NeRF view's refinement schedules (:class:`pienerf.render.RefinementSchedule`), one per client (a browser
    tab), all under one frame budget; thread-safe, as a viewer's server threads drop clients while the loop renders.

    Args:
        frame_budget: seconds a frame of the NeRF mode may take while things move, step and render together; the
            render's resolution adapts to hold it.
    """

    def __init__(self, frame_budget: float = 1.0 / 30.0):
        self._frame_budget = RefinementSchedule.check_frame_budget(frame_budget)
        self._schedules: dict[object, RefinementSchedule] = {}
        self._lock = threading.Lock()

    @property
    def frame_budget(self) -> float:
        """Seconds a frame of the NeRF mode may take while things move (a new value starts every schedule again)."""
        return self._frame_budget

    @frame_budget.setter
    def frame_budget(self, seconds: float) -> None:
        self._frame_budget = RefinementSchedule.check_frame_budget(seconds)
        self.drop()

    def of(self, client) -> RefinementSchedule:
        """``client``'s schedule, started at its first frame."""
        with self._lock:
            return self._schedules.setdefault(client, RefinementSchedule(frame_budget=self._frame_budget))

    def drop(self, client=None) -> None:
        """Forget ``client``'s schedule (a closed tab), or every schedule (``None``: a new render mode or budget)."""
        with self._lock:
            if client is None:
                self._schedules.clear()
            else:
                self._schedules.pop(client, None)


def render_nerf_in_budget(app: DemoApp, schedule: RefinementSchedule, cameras, level: int) -> Frame:
    """The warped NeRF of ``app``'s simulation seen by ``cameras`` at downscale ``level``. The render's time and this
    frame's step (none while paused) go to ``schedule``, which picks the next moving level by them."""
    sim = app.simulation
    clock = time.perf_counter()
    frame = sim.render(cameras, 0, "nerf", downscale=level)  # synchronised: the frame is ready when it returns
    schedule.record(level, time.perf_counter() - clock, 0.0 if app.paused else sim.last_report.time_step)
    return frame


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


def _fit_in_child(scene: str, fit, cache_dir: str | None, device: str, messages) -> None:
    """The body of a :class:`NerfJob`'s process: fit (or load) the scene's NeRF into the cache, reporting."""
    backend.init(device)
    try:
        scene_nerf(scene, fit or NerfFit(), cache_dir, lambda stage, fraction: messages.put((stage, fraction)))
    except Exception as error:  # reported to the parent, which shows it
        messages.put((f"{type(error).__name__}: {error}", None))
        return
    messages.put(("", 1.0))


class NerfJob:
    """The fit of an embedded scene's NeRF (:func:`pienerf.scenes.scene_nerf`) in a separate process.

    The process writes the checkpoint to the scene cache, where :func:`load_nerf` then finds it. :meth:`poll`
    never blocks.

    Args:
        scene: one of :data:`pienerf.scenes.SCENES`.
        fit: the fitting settings (default :class:`pienerf.nerf.fitting.NerfFit`).
        cache_dir: the cache root (as :func:`pienerf.scenes.scene_nerf`).
        device: where the process fits (default: this process's device).

    Attributes:
        finished: the process has ended.
        error: why it failed, or ``None``.
    """

    def __init__(self, scene: str, fit=None, cache_dir: str | None = None, device: str | None = None):
        if scene not in SCENES:
            raise ValueError(f"no NeRF can be fitted to {scene!r}: embedded scenes are {', '.join(SCENES)}")
        context = multiprocessing.get_context("spawn")  # a fresh interpreter: Taichi and torch state are per process
        self._messages = context.Queue()
        device = device or backend.current_device() or backend.default_device()
        self._process = context.Process(
            target=_fit_in_child, args=(scene, fit, cache_dir, device, self._messages), daemon=True
        )
        self._process.start()
        self.finished = False
        self.error: str | None = None

    def poll(self) -> list[tuple[str, float]]:
        """Progress reported since the last call, as ``(stage, fraction)``; sets :attr:`finished` and :attr:`error`."""
        updates = []
        alive = self._process.is_alive()
        while True:
            try:
                stage, fraction = self._messages.get_nowait()
            except queue.Empty:
                break
            if fraction is None:
                self.error, self.finished = stage, True
            elif stage == "" and fraction == 1.0:
                self.finished = True
            else:
                updates.append((stage, fraction))
        if not alive and not self.finished:
            self.finished = True
            self.error = f"the fitting process ended with exit code {self._process.exitcode}"
        if self.finished:
            self._process.join(5.0)
        return updates

    def cancel(self) -> None:
        """Stop the process (a partly written checkpoint is never left: the fit saves atomically)."""
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(5.0)
        self.finished = True


class Viewer(Protocol):
    """What the demo loop needs from a display."""

    def attach(self, app: DemoApp) -> None: ...

    def update(self, app: DemoApp) -> None: ...

    def report(self, message: str) -> None: ...

    def show_progress(self, stage: str, fraction: float | None) -> None:
        """Show the progress of slow work (``fraction`` in [0, 1]), or hide it (``None``)."""

    def has_clients(self) -> bool:
        """Whether any page is connected (with none the loop sleeps until one connects)."""

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
        self.commands = CommandQueue()
        self.stop = threading.Event()
        self.paused = False
        self.still_frames = 0  # consecutive frames the body stayed still with nothing to do
        self._wake = threading.Event()
        self.fps = 0.0
        self.errors: list[str] = []
        self.nerf_job: NerfJob | None = None
        self._nerf_ready: Callable[[], object] | None = None
        viewer.attach(self)

    def submit(self, what: str, command: Callable[[], object], key: str | None = None, heavy: bool = False) -> None:
        """Queue ``command`` to run in the loop thread between steps (``key`` and ``heavy`` as
        :meth:`CommandQueue.put`, which raises ValueError when too many wait); wakes a sleeping loop."""
        self.commands.put(what, command, key, heavy)
        self.wake()

    def wake(self) -> None:
        """Something changed (a command, a tab, a camera): the loop runs its frames again at once."""
        self.still_frames = 0
        self._wake.set()

    def run_commands(self) -> None:
        """Run one frame's commands (:meth:`CommandQueue.take`); later ones wait for the next frame."""
        for what, command in self.commands.take():
            self._run(what, command)
            self.still_frames = 0

    @property
    def resting(self) -> bool:
        """Whether the loop may sleep: no page is connected, or the body stayed still (:data:`REST_SPEED`) for
        :data:`REST_FRAMES` frames with nothing dragged, no command waiting and no NeRF being fitted."""
        if self.nerf_job is not None or not self.commands.empty():
            return False
        return not self.viewer.has_clients() or self.still_frames >= REST_FRAMES

    def _run(self, what: str, command: Callable[[], object]) -> None:
        try:
            command()
        except Exception as error:  # a bad request must not stop the loop
            message = f"{what} failed: {error}"
            self.errors.append(message)
            self.viewer.report(message)

    def fit_nerf(self, then: Callable[[], object]) -> None:
        """Make the ``"nerf"`` render mode available, then call ``then`` (in the loop thread).

        A given checkpoint, or one already loaded, is used at once. Otherwise the scene's NeRF is fitted (or loaded
        from the cache) by a :class:`NerfJob` while the loop goes on stepping; ``then`` runs once it is loaded.
        """
        sim = self.simulation
        if "nerf" in sim.render_backends or self.nerf_options.get("checkpoint") is not None:
            load_nerf(sim, **self.nerf_options)
            then()
            return
        if self.nerf_job is not None:
            raise ValueError("the NeRF is already being fitted (see the progress bar); it shows when ready")
        if sim.config.scene not in SCENES:
            load_nerf(sim, **self.nerf_options)  # raises with the fix for a mesh scene
        options = self.nerf_options
        self.nerf_job = NerfJob(sim.config.scene, options.get("fit"), options.get("cache_dir"))
        self._nerf_ready = then
        self.viewer.show_progress("NeRF: starting the fit", 0.0)
        self.viewer.report("fitting the NeRF in the background; the simulation goes on")

    def _poll_nerf(self) -> None:
        job = self.nerf_job
        if job is None:
            return
        for stage, fraction in job.poll():
            self.viewer.show_progress(f"NeRF: {stage}", fraction)
        if not job.finished:
            return
        self.nerf_job, then = None, self._nerf_ready
        self.viewer.show_progress("", None)
        if job.error is not None:
            self.errors.append(f"NeRF fit failed: {job.error}")
            self.viewer.report(self.errors[-1])
            return
        self._run("NeRF load", lambda: (load_nerf(self.simulation, **self.nerf_options), then()))

    def close(self) -> None:
        """Stop a fit in progress and close the viewer."""
        self.stop.set()
        self._wake.set()
        if self.nerf_job is not None:
            self.nerf_job.cancel()
            self.nerf_job = None
        self.viewer.close()

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
        """One frame: commands, the progress of a background fit, one step unless paused, display."""
        self.run_commands()
        self._poll_nerf()
        start = time.perf_counter()
        if not self.paused:
            self.simulation.step()
        still = self.paused or self.simulation.max_speed() < REST_SPEED
        self.still_frames = self.still_frames + 1 if still and not self.simulation.dragging else 0
        self.viewer.update(self)
        elapsed = time.perf_counter() - start
        self.fps = 0.9 * self.fps + 0.1 / max(elapsed, 1e-6) if self.fps else 1.0 / max(elapsed, 1e-6)

    def run(self, steps: int | None = None, frame_seconds: float = 1.0 / 30.0) -> None:
        """Loop until :attr:`stop` is set (or ``steps`` frames ran), at most one frame per ``frame_seconds``.

        Without ``steps`` the loop sleeps while :attr:`resting` and wakes at the next :meth:`wake` (a command, a tab
        connecting, a camera move): an unwatched or still body costs no frames."""
        count = 0
        while not self.stop.is_set() and (steps is None or count < steps):
            if steps is None and self.resting:
                self._wake.clear()
                if self.resting:  # nothing woke it between the check and the clear
                    self._wake.wait(_SLEEP_CHECK_SECONDS)
                continue
            start = time.perf_counter()
            self.tick()
            count += 1
            if steps is None:
                self._wake.clear()
                self._wake.wait(max(0.0, frame_seconds - (time.perf_counter() - start)))
