"""The simulation loop behind an interactive viewer: viewer events become commands run between steps.

A front end (:class:`pienerf.viewer.viser_viewer.ViserViewer`, :class:`pienerf.viewer.meshcat_viewer.MeshcatViewer`)
implements :class:`Viewer` and only translates events: it queues commands with :meth:`DemoApp.submit`, which the
loop runs between steps through the :class:`pienerf.session.Simulation` verbs. A command that fails (a malformed
message, a bad value) is reported to the viewer and the loop goes on.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from pienerf.nerf.fitting import NerfFit
from pienerf.render.previews import Frame
from pienerf.render.refinement import RefinementSchedule
from pienerf.scenes import SCENES
from pienerf.viewer.nerf_job import NerfJob, load_nerf, shipped_nerf

__all__ = [
    "CONTROL_RANGES",
    "MAX_PENDING_COMMANDS",
    "RENDER_MODES",
    "REST_FRAMES",
    "REST_SPEED",
    "CommandQueue",
    "DemoApp",
    "NerfSchedules",
    "Viewer",
    "control_value",
    "nerf_image",
    "number_in",
    "picked_text",
    "render_nerf_in_budget",
    "si_text",
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
    return number_in(value, name.replace("_", " "), *CONTROL_RANGES[name])


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


def nerf_image(app: DemoApp, schedule: RefinementSchedule, cameras, level: int, background: torch.Tensor):
    """``(image, frame)``: the warped NeRF (:func:`render_nerf_in_budget`) over ``background`` (RGB in [0, 1]) as an
    ``[H, W, 3]`` uint8 array, and the :class:`pienerf.render.previews.Frame` it came from (for its depth)."""
    frame = render_nerf_in_budget(app, schedule, cameras, level)
    alpha = frame.rgba[..., 3:]
    rgb = frame.rgba[..., :3] * alpha + (1.0 - alpha) * background.to(alpha)
    return (rgb.clamp(0, 1) * 255).round().byte().cpu().numpy(), frame


def picked_text(hit) -> str:
    """The message of a pick: the picked material point (rest space, m) or garment vertex, or that nothing was hit."""
    if hit is None:
        return "picked nothing"
    if hasattr(hit, "vertex"):
        return f"picked garment vertex {hit.vertex} at {np.round(hit.world.numpy(), 3).tolist()} (m)"
    return f"picked {np.round(hit.rest.numpy(), 3).tolist()} (rest, m)"


def number_in(value, what: str, lo: float, hi: float) -> float:
    """``value`` as a float when it is a number in ``[lo, hi]`` (not a bool), else a ValueError naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"{what} must be a number in [{lo:g}, {hi:g}], got {str(value)[:80]}")
    return float(value)


def vector3(value, what: str) -> np.ndarray:
    """A finite 3-vector from a client message, or a ValueError naming the field."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} is not a 3-vector: {value!r}") from None
    if array.shape != (3,) or not np.isfinite(array).all():
        raise ValueError(f"{what} must be 3 finite numbers, got {value!r}")
    return array


class Viewer(Protocol):
    """What the demo loop needs from a display."""

    nerf_schedules: NerfSchedules

    def attach(self, app: DemoApp) -> None: ...

    def update(self, app: DemoApp) -> None: ...

    def report(self, message: str) -> None: ...

    def show_progress(self, stage: str, fraction: float | None) -> None:
        """Show the progress of slow work (``fraction`` in [0, 1]), or hide it (``None``)."""

    def detach(self) -> None:
        """Take the scene and its controls off the page (a scene switch attaches the next one)."""

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
        scene: the name of the scene shown (the scene menu shows it).
        scenes: the names the scene menu offers, ``scene`` among them; empty: no menu.
        build_scene: ``build_scene(name, progress)``, the simulation of a scene of ``scenes``
            (:meth:`switch_scene`); ``progress(stage, fraction)`` follows the build.
    """

    def __init__(
        self,
        simulation,
        viewer: Viewer,
        render_mode: str = "mesh",
        nerf_options: dict | None = None,
        scene: str | None = None,
        scenes: tuple[str, ...] = (),
        build_scene: Callable[[str, Callable[[str, float], None]], object] | None = None,
    ):
        if render_mode not in RENDER_MODES:
            raise ValueError(f"unknown render mode {render_mode!r}; valid: {', '.join(RENDER_MODES)}")
        if scenes and (scene not in scenes or build_scene is None):
            raise ValueError(f"a scene menu needs the scene shown ({scene!r}) among {list(scenes)} and a builder")
        self.simulation = simulation
        self.scene = scene if scene is not None else getattr(simulation.config, "scene", "")
        self.scenes = tuple(scenes)
        self._build_scene = build_scene
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
        self._nerf_shown = 0  # fits of the current job loaded into the simulation
        self._refinement_started = False  # the shipped NeRF's background refinement
        viewer.attach(self)

    def submit(
        self,
        what: str,
        command: Callable[[], object],
        key: str | None = None,
        heavy: bool = False,
        report: Callable[[object], str] | None = None,
    ) -> None:
        """Queue ``command`` (a :class:`pienerf.session.Simulation` verb) to run in the loop thread between steps
        (``key`` and ``heavy`` as :meth:`CommandQueue.put`, which raises ValueError when too many wait); wakes a
        sleeping loop. ``report(result)``, when given, is the message the viewer shows once the command ran; after a
        ``heavy`` command (which may show progress) the progress bar is hidden."""
        if report is not None or heavy:
            verb = command

            def command() -> None:
                result = verb()
                if heavy and self.nerf_job is None:
                    self.viewer.show_progress("", None)
                if report is not None:
                    self.viewer.report(report(result))

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

        A given checkpoint, one already loaded, or the NeRF that ships with the scene
        (:func:`pienerf.viewer.nerf_job.shipped_nerf`, when no other fit is asked for) is used at once; after the
        shipped one the default fit is made (or loaded from the cache) in the background and replaces it when
        ready. Otherwise the scene's NeRF is fitted (or loaded from the cache) by a
        :class:`pienerf.viewer.nerf_job.NerfJob` while the loop goes on stepping; ``then`` runs once the first
        (coarse) NeRF is loaded, and the refined one replaces it when ready.
        """
        sim, options = self.simulation, self.nerf_options
        if self.nerf_job is not None:
            raise ValueError("the NeRF is already being fitted (see the progress bar); it shows when ready")
        shipped = options.get("checkpoint") is None and shipped_nerf(sim.config.scene, options.get("fit"))
        if "nerf" in sim.render_backends or options.get("checkpoint") is not None or shipped:
            load_nerf(sim, **options)
            then()
            if shipped and options.get("fit") is None and not self._refinement_started:
                self._refinement_started = True
                self._start_nerf_job(NerfFit(), then)
            return
        if sim.config.scene not in SCENES:
            load_nerf(sim, **options)  # raises with the fix for a mesh scene
        self._start_nerf_job(options.get("fit"), then)

    def _start_nerf_job(self, fit, then: Callable[[], object]) -> None:
        self.nerf_job = NerfJob(self.simulation.config.scene, fit, self.nerf_options.get("cache_dir"))
        self._nerf_ready, self._nerf_shown = then, 0
        self.viewer.show_progress("NeRF: starting the fit", 0.0)
        self.viewer.report("fitting the NeRF in the background; the simulation goes on")

    def _poll_nerf(self) -> None:
        job = self.nerf_job
        if job is None:
            return
        for stage, fraction in job.poll():
            step = f" ({job.ready + 1} of {len(job.fits)})" if len(job.fits) > 1 else ""
            self.viewer.show_progress(f"NeRF{step}: {stage}", fraction)
        if job.ready > self._nerf_shown:  # a fit is in the cache: show it (the first), or put it in its place
            index, self._nerf_shown = job.ready - 1, job.ready
            options = {**self.nerf_options, "fit": job.fits[index]}
            if "nerf" not in self.simulation.render_backends:
                self._run("NeRF load", lambda: (load_nerf(self.simulation, **options), self._nerf_ready()))
            else:
                self._run("NeRF refinement", lambda: load_nerf(self.simulation, replace=True, **options))
                self.viewer.nerf_schedules.drop()  # every view is rendered again with it
                self.wake()
                self.viewer.report("the refined NeRF replaces the first one")
        if not job.finished:
            return
        self.nerf_job = None
        self.viewer.show_progress("", None)
        if job.error is not None:
            self.errors.append(f"NeRF fit failed: {job.error}")
            self.viewer.report(self.errors[-1])

    def check_scene(self, name) -> str:
        """``name`` when the scene menu offers it, else a ValueError naming the scenes it offers."""
        if not self.scenes:
            raise ValueError("this viewer has no scene menu; start it with --scene NAME")
        if not isinstance(name, str) or name not in self.scenes:
            raise ValueError(f"unknown scene {str(name)[:40]!r}; valid: {', '.join(self.scenes)}")
        return name

    def choose_scene(self, name) -> None:
        """Queue the switch to scene ``name`` (checked here, on the caller's thread: a bad name raises ValueError
        and queues nothing); a later choice waiting with it replaces it."""
        name = self.check_scene(name)
        self.submit(f"scene {name}", lambda: self.switch_scene(name), key="scene", heavy=True)

    def switch_scene(self, name: str) -> None:
        """Build scene ``name`` (progress in the viewer) and show it in place of the current one, in the loop thread.

        The build happens before anything is taken down: a build that fails raises ValueError with its error and
        the current scene stays, its state untouched. A NeRF fit in progress is stopped; the new scene shows its
        mesh, and a ``checkpoint`` of :attr:`nerf_options` (trained on the first scene) is forgotten.
        """
        name = self.check_scene(name)
        self.viewer.report(f"building the {name} scene (the {self.scene} scene waits until it is ready)")
        progress = lambda stage, fraction: self.viewer.show_progress(f"{name}: {stage}", fraction)  # noqa: E731
        progress("starting", 0.0)
        try:
            simulation = self._build_scene(name, progress)
        except Exception as error:
            self.viewer.show_progress("", None)
            raise ValueError(f"the {name} scene could not be built ({error}); still showing {self.scene}") from error
        if self.nerf_job is not None:
            self.nerf_job.cancel()
            self.nerf_job = None
        self._refinement_started, self._nerf_shown = False, 0
        shown = (self.simulation, self.scene, self.render_mode, self.paused)
        self.viewer.detach()
        self.simulation, self.scene, self.render_mode, self.paused = simulation, name, "mesh", False
        try:
            self.viewer.attach(self)
        except Exception:  # the page cannot show it: back to the scene it showed
            self.viewer.detach()
            self.simulation, self.scene, self.render_mode, self.paused = shown
            self.viewer.attach(self)
            raise
        self.nerf_options.pop("checkpoint", None)
        self.still_frames = 0

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
            self.viewer.report(picked_text(self.simulation.pick(origin, direction)))

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
