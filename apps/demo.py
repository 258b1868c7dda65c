"""Interactive drag-and-force viewer of a Q-GMLS body (PIE-NeRF Fig. 1, 5).

    python -m apps.demo [--scene plant|teapot|jelly|cloth|sculpture|PATH] [--device cpu|cuda]
                        [--host 127.0.0.1] [--port 8080] [--viewer meshcat|viser] [--smoke]
                        [--render mesh|particles|nerf] [--nerf-checkpoint PATH] [--cache-dir DIR]

``meshcat`` (default) serves meshcat's own three.js client under a page of the project
(:class:`pienerf.viewer.meshcat_viewer.MeshcatViewer`): the deformed scene mesh updated every frame, a panel with the
material (Young's modulus, Poisson ratio, density, model), damping, gravity, the kernel count (re-sampling shows
progress), pin / push / cut / release / reset buttons, the render mode, the frame rate, the time breakdown and the
last message. Press on the body and drag: the press picks a material point and the pointer's ray, at the picked
depth, is the drag target until release; a click (no move) keeps the point picked for pin / push / cut. ``viser``
serves the same panel through viser, with the particles and the integrator points as toggles; a click picks, a
further click moves the target onto that ray at the picked depth, and a gizmo at the target moves it in 3-D. The
spring of :class:`pienerf.picking.DragController` pulls the body. ``--smoke`` starts the viewer, runs a few steps
headless and exits 0.

``--render`` picks what the page shows (the panel's "render" menu switches it later): ``mesh`` (default) and
``particles`` are drawn by the browser; ``nerf`` is a NeRF of the scene warped by the body's deformation
(quadratic ray warping, PIE-NeRF Eq. 19–21), rendered on the server from each client's camera and shown as the
page's background image with its depth. While the body or the camera moves it is rendered at a quarter of the
resolution, then once at full resolution when still. The NeRF is trained on the scene's own rendered views the
first time, with progress in the terminal (or in the panel when switched on there; the simulation waits), and
cached as a checkpoint under the scene cache (``--cache-dir``, default ``$PIE_CACHE_DIR`` or
``~/.cache/pie-physavatar``), so later starts load it; ``--nerf-checkpoint`` loads a given one instead (trained in
the scene's coordinates). The default stays ``mesh``: on this project's 2-core CPU the plant's NeRF (48 views of
64², 1000 steps of 2048 rays; 27.4 dB on held-out views) took 91 s to fit, over the minute a start may take; a
later start loads it in about a second. A 320 × 240 view then took 0.4 s to render and its 80 × 60 preview
0.06–0.09 s. In viser's NeRF mode the body is picked by clicking (the mouse-drag handle belongs to the hidden mesh).

Viewer events become commands queued to the simulation loop, which runs them between steps; a command that fails
(a malformed message, a bad value) is reported in the panel and the loop goes on, and a client that disconnects
only leaves its GUI behind.
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from kernels import backend
from pienerf.viewer.loop import RENDER_MODES, RefinementSchedule, load_nerf
from pienerf.viewer.meshcat_viewer import MeshcatViewer

SMOKE = {"kernel_count": 6, "particle_radius": 0.06, "lloyd_iterations": 0}


def _smoke_fit():
    """A NeRF fit of a few seconds for ``--smoke`` (16 views of 32², 60 steps, a small hash grid)."""
    from kernels.hashgrid import HashGridConfig
    from pienerf.nerf import NGPConfig
    from pienerf.nerf_backend import NerfFit
    from pienerf.train import TrainConfig

    ngp = NGPConfig(
        hashgrid=HashGridConfig(levels=6, features=2, log2_table_size=12, base_resolution=8, max_resolution=64),
        density_hidden=16,
        color_hidden=16,
        color_layers=1,
        grid_resolution=32,
        samples_per_diagonal=128,
    )
    return NerfFit(ngp=ngp, train=TrainConfig(steps=60, batch_rays=512, grid_warmup_steps=16), views=16, resolution=32)


def viser_cameras(position, wxyz, fov: float, aspect: float, height: int):
    """:class:`pienerf.data.Cameras` (one view, OpenGL axes) of a viser client's camera, ``height`` pixels high.

    viser gives the camera-to-world rotation as a quaternion ``wxyz`` in OpenCV axes (x right, y down, looking
    along +z), the position in metres and the vertical field of view ``fov`` in radians; ``aspect`` is width over
    height.
    """
    from viser import transforms

    from pienerf.data import Cameras

    if not (height >= 1 and aspect > 0 and 0 < fov < math.pi):
        raise ValueError(f"need height >= 1 px, aspect > 0 and 0 < fov < pi rad, got {height}, {aspect}, {fov}")
    rotation = transforms.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rotation, _vector(position, "camera position")
    width = max(1, int(round(height * aspect)))
    focal = torch.tensor([0.5 * height / math.tan(0.5 * fov)])
    return Cameras(
        torch.tensor(c2w, dtype=torch.float32)[None],
        focal,
        focal.clone(),
        torch.tensor([0.5 * width]),
        torch.tensor([0.5 * height]),
        width,
        height,
    )


def _vector(value, what: str) -> np.ndarray:
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
        self.scripted_drag: Callable[[float], torch.Tensor] | None = None
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
        origin = _vector(ray_origin, "click ray origin")
        direction = _vector(ray_direction, "click ray direction")
        drag = self.simulation.interaction.drag
        if drag.dragging:
            self.simulation.drag_to(origin, direction)
        else:
            hit = self.simulation.pick(origin, direction)
            self.viewer.report("picked nothing" if hit is None else f"picked {np.round(hit.rest.numpy(), 3)}")

    def tick(self) -> None:
        """One frame: commands, one step unless paused, display."""
        self.run_commands()
        start = time.perf_counter()
        if not self.paused:
            if self.scripted_drag is not None:
                self.simulation.drag_to(target=self.scripted_drag(self.simulation.time))
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


class ViserViewer:
    """The browser viewer: a viser server with the scene, the controls panel and click-to-drag.

    Args:
        host, port: where the page is served.
        nerf_height: height in pixels of the NeRF images rendered for each client (width from its aspect).
        background: colour behind the NeRF render, RGB in [0, 1].
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, nerf_height: int = 240, background=(1.0, 1.0, 1.0)):
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.app: DemoApp | None = None
        self._gizmo = None
        self._gizmo_sync = False
        self.nerf_height = int(nerf_height)
        self.background = torch.tensor(background, dtype=torch.float32)
        self._schedules: dict[int, RefinementSchedule] = {}
        self.nerf_renders: list[int] = []  # downscale of every NeRF image sent, in order
        self.last_nerf_image: np.ndarray | None = None  # [H, W, 3] uint8, the latest one

    # -- construction ----------------------------------------------------------------------------

    def attach(self, app: DemoApp) -> None:
        self.app = app
        server, sim = self.server, app.simulation
        server.scene.set_up_direction("+y")
        faces = sim.mesh_faces.numpy().astype(np.uint32)
        self._faces = faces
        self._colors = (sim.mesh_colors.numpy() * 255).astype(np.uint8)
        self.mesh = server.scene.add_mesh_simple(
            "/body", sim.deformed_mesh_vertices().numpy(), faces, color=(200, 170, 120)
        )
        self.particles = server.scene.add_point_cloud(
            "/particles",
            sim.particle_positions().numpy(),
            (sim.particle_colors.numpy() * 255).astype(np.uint8),
            point_size=0.6 * sim.particle_radius,
            visible=False,
        )
        self.ips = server.scene.add_point_cloud(
            "/integrator_points",
            sim.integrator_positions().numpy(),
            (230, 40, 40),
            point_size=1.2 * sim.particle_radius,
            visible=False,
        )
        self.ground = server.scene.add_grid("/ground", width=4.0, height=4.0, plane="xz", position=(0.0, 0.0, 0.0))
        self._build_gui(app)
        server.scene.on_click()(self._on_click)
        self.mesh.on_drag("left")(self._on_drag)
        server.on_client_connect(self._on_connect)
        self._show(app.render_mode)

    def _build_gui(self, app: DemoApp) -> None:
        gui, sim = self.server.gui, app.simulation
        material = sim.material
        with gui.add_folder("Material"):
            self.young = gui.add_slider("Young's modulus log10(Pa)", 3.0, 7.0, 0.1, math.log10(material.young_modulus))
            self.poisson = gui.add_slider("Poisson ratio", 0.0, 0.49, 0.01, material.poisson_ratio)
            self.density = gui.add_slider("density (kg/m³)", 100.0, 3000.0, 50.0, material.density)
            self.model = gui.add_dropdown(
                "model", ("neo_hookean", "arap", "stvk", "fixed_corotated"), initial_value=material.model
            )
            self.damping = gui.add_slider("damping α (1/s)", 0.0, 20.0, 0.5, sim.config.rayleigh_alpha)
            self.gravity = gui.add_slider("gravity (m/s²)", 0.0, 20.0, 0.1, -sim.config.gravity[1])
        with gui.add_folder("Discretisation"):
            self.kernels = gui.add_slider("kernels", 4, 128, 1, sim.model.basis.kernel_count)
            self.resample = gui.add_button("resample")
            self.progress = gui.add_progress_bar(100.0, visible=False)
        with gui.add_folder("Interaction"):
            self.release = gui.add_button("release")
            self.pin = gui.add_button("pin picked region")
            self.push = gui.add_button("constant force at picked point")
            self.cut = gui.add_button("cut through picked point")
            self.reset = gui.add_button("reset")
        with gui.add_folder("View"):
            self.render_mode = gui.add_dropdown("render", RENDER_MODES, initial_value=app.render_mode)
            self.show_mesh = gui.add_checkbox("mesh", True)
            self.show_particles = gui.add_checkbox("particles", False)
            self.show_ips = gui.add_checkbox("kernels and integrator points", False)
        self.stats = gui.add_markdown("starting")
        self.message = gui.add_markdown("click the body to pick, click again to drag")

        def material_changed(_event) -> None:
            values = dict(
                young_modulus=10.0**self.young.value,
                poisson_ratio=self.poisson.value,
                density=self.density.value,
                model=self.model.value,
                damping=self.damping.value,
                gravity=(0.0, -self.gravity.value, 0.0),
            )
            app.submit("material change", lambda: sim.set_material(**values))

        for handle in (self.young, self.poisson, self.density, self.model, self.damping, self.gravity):
            handle.on_update(material_changed)
        self.resample.on_click(lambda _e: app.submit("resample", lambda: self._resample(int(self.kernels.value))))
        self.release.on_click(lambda _e: app.submit("release", self._release))
        self.pin.on_click(lambda _e: app.submit("pin", lambda: sim.interaction.pin_picked(sim.state.q)))
        self.push.on_click(lambda _e: app.submit("force", self._push))
        self.cut.on_click(lambda _e: app.submit("cut", lambda: sim.cut_picked((0.0, 1.0, 0.0))))
        self.reset.on_click(lambda _e: app.submit("reset", sim.reset))
        self.show_mesh.on_update(lambda _e: setattr(self.mesh, "visible", self.show_mesh.value))
        self.show_particles.on_update(lambda _e: setattr(self.particles, "visible", self.show_particles.value))
        self.show_ips.on_update(lambda _e: setattr(self.ips, "visible", self.show_ips.value))
        self.render_mode.on_update(
            lambda _e: app.submit("render mode", lambda mode=self.render_mode.value: self._set_render_mode(mode))
        )

    # -- events ----------------------------------------------------------------------------------

    def _on_click(self, event) -> None:
        try:
            origin, direction = _vector(event.ray_origin, "ray origin"), _vector(event.ray_direction, "ray direction")
        except ValueError as error:
            self.report(f"ignored a malformed click: {error}")
            return
        self.app.submit("click", lambda: self.app.click(origin, direction))

    def _on_drag(self, event) -> None:
        """A mouse drag on the mesh: pick under the press, follow the pointer on the camera-aligned plane
        through the picked point, let go at release."""
        try:
            if event.phase == "start":
                origin = _vector(event.client.camera.position, "camera position")
                direction = _vector(event.start_position, "drag start") - origin
                self.app.submit("drag start", lambda: self.app.simulation.pick(origin, direction))
            elif event.phase == "update":
                target = _vector(event.end_position, "drag position")
                self.app.submit("drag", lambda: self.app.simulation.drag_to(target=target))
            else:
                self.app.submit("drag end", self._release)
        except ValueError as error:
            self.report(f"ignored a malformed drag: {error}")

    def _on_connect(self, client) -> None:
        sim = self.app.simulation
        centre = sim.centre.double().numpy()
        client.camera.up_direction = (0.0, 1.0, 0.0)
        client.camera.position = centre + np.array([0.0, 0.3, 2.6])
        client.camera.look_at = centre

    def _set_render_mode(self, mode: str) -> None:
        """Switch what the page shows; the NeRF is loaded (or trained, with progress in the panel) the first time."""
        app = self.app
        if mode == "nerf" and "nerf" not in app.simulation.render_backends:
            self.progress.visible = True

            def progress(stage: str, fraction: float) -> None:
                self.progress.value = 100.0 * fraction
                self.report(stage)

            try:
                load_nerf(app.simulation, progress=progress, **app.nerf_options)
            except Exception:
                self.render_mode.value = app.render_mode  # stay in the mode shown
                raise
            finally:
                self.progress.visible = False
        app.render_mode = mode
        self._show(mode)
        self.report(f"showing the {mode}")

    def _show(self, mode: str) -> None:
        """Scene nodes of a render mode: the browser's mesh or particles, or the server's NeRF image."""
        self.show_mesh.value = mode == "mesh"
        self.show_particles.value = mode == "particles"
        self.mesh.visible, self.particles.visible = mode == "mesh", mode == "particles"
        self.ground.visible = mode != "nerf"  # the NeRF image has its own ground and shadow
        if mode != "nerf":
            self.server.scene.set_background_image(None)
        self._schedules.clear()

    def _update_nerf(self, sim) -> None:
        """Render the warped NeRF from every client's camera: coarse while things move, refined when still."""
        renderer = sim.render_backends["nerf"]
        for client_id, client in self.server.get_clients().items():
            camera = client.camera
            try:
                view = (
                    tuple(np.round(camera.position, 5)),
                    tuple(np.round(camera.wxyz, 5)),
                    round(camera.fov, 5),
                    round(camera.aspect, 4),
                )
            except AssertionError:  # the client has not sent its camera yet
                continue
            level = self._schedules.setdefault(client_id, RefinementSchedule()).next(sim.state.q, view)
            if level is None:
                continue
            renderer.downscale = level
            cameras = viser_cameras(camera.position, camera.wxyz, camera.fov, camera.aspect, self.nerf_height)
            frame = sim.render(cameras, 0, "nerf")
            alpha = frame.rgba[..., 3:]
            rgb = frame.rgba[..., :3] * alpha + (1.0 - alpha) * self.background.to(alpha)
            # viser composites with the depth along the optical axis: the ray length times cos(off-axis angle).
            rows, cols = torch.meshgrid(
                torch.arange(cameras.height) + 0.5, torch.arange(cameras.width) + 0.5, indexing="ij"
            )
            slope = torch.stack([(cols - cameras.cx[0]) / cameras.fx[0], (rows - cameras.cy[0]) / cameras.fy[0]])
            z = frame.depth.cpu() / torch.sqrt(1.0 + (slope**2).sum(0))
            z = torch.where(torch.isfinite(z), z, 100.0)
            image = (rgb.clamp(0, 1) * 255).round().byte().cpu().numpy()
            client.scene.set_background_image(image, format="jpeg", depth=z.numpy())
            self.nerf_renders.append(level)
            self.last_nerf_image = image

    def _resample(self, kernel_count: int) -> None:
        self.progress.visible = True
        sim = self.app.simulation

        def progress(stage: str, fraction: float) -> None:
            self.progress.value = 100.0 * fraction
            self.report(f"resampling: {stage}")

        sim.resample(kernel_count, progress)
        self.progress.visible = False
        self._remove_gizmo()

    def _release(self) -> None:
        self.app.simulation.release()
        self._remove_gizmo()

    def _push(self) -> None:
        sim = self.app.simulation
        weight = sim.material.density * float(sim.model.volume.sum()) * 9.81
        sim.interaction.push_picked((0.0, 0.0, -0.5 * weight))
        self._remove_gizmo()

    def _remove_gizmo(self) -> None:
        if self._gizmo is not None:
            self._gizmo.remove()
            self._gizmo = None

    def _sync_gizmo(self) -> None:
        drag = self.app.simulation.interaction.drag
        if not drag.dragging:
            self._remove_gizmo()
            return
        target = drag.target.numpy()
        if self._gizmo is None:
            self._gizmo = self.server.scene.add_transform_controls(
                "/drag_target", scale=0.2, disable_rotations=True, position=target
            )

            def moved(_event, gizmo=self._gizmo) -> None:
                position = np.asarray(gizmo.position, dtype=np.float64)
                self.app.submit("gizmo drag", lambda: self.app.simulation.drag_to(target=position))

            self._gizmo.on_update(moved)
        elif not np.allclose(self._gizmo.position, target):
            self._gizmo.position = target

    # -- per frame -------------------------------------------------------------------------------

    def update(self, app: DemoApp) -> None:
        sim = app.simulation
        if app.render_mode == "nerf" and "nerf" in sim.render_backends:
            self._update_nerf(sim)
        with self.server.atomic():
            if self.mesh.visible:
                self.mesh.vertices = sim.deformed_mesh_vertices().numpy()
            if self.particles.visible:
                self.particles.points = sim.particle_positions().numpy()
            if self.ips.visible:
                self.ips.points = sim.integrator_positions().numpy()
        self._sync_gizmo()
        report = sim.last_report
        seconds = sim.time_breakdown()["seconds_per_step"]
        self.stats.content = (
            f"**{app.fps:.1f} fps**, t = {sim.time:.2f} s, {sim.model.basis.kernel_count} kernels, "
            f"{report.iterations} Newton iterations  \n"
            + ", ".join(f"{name} {1e3 * value:.1f} ms" for name, value in seconds.items())
        )

    def report(self, message: str) -> None:
        self.message.content = message

    def close(self) -> None:
        self.server.stop()


def build_app(
    scene: str,
    viewer_name: str,
    host: str,
    port: int,
    smoke: bool,
    render: str = "mesh",
    nerf_checkpoint: str | None = None,
    cache_dir: str | None = None,
    progress=None,
) -> DemoApp:
    """The simulation of ``scene`` behind the chosen viewer, showing ``render`` (:data:`RENDER_MODES`).

    With ``render="nerf"`` the NeRF is loaded from ``nerf_checkpoint`` or fitted to the scene (a few-second fit
    with ``smoke``) before the viewer starts; ``progress(stage, fraction)`` follows the set-up.
    """
    from pienerf.session import Simulation, SimulationConfig

    if render not in RENDER_MODES:
        raise ValueError(f"unknown render mode {render!r}; valid: {', '.join(RENDER_MODES)}")
    simulation = Simulation(SimulationConfig(scene=scene, **(SMOKE if smoke else {})), progress)
    nerf_options = {"checkpoint": nerf_checkpoint, "fit": _smoke_fit() if smoke else None, "cache_dir": cache_dir}
    if render == "nerf":
        load_nerf(simulation, progress=progress, **nerf_options)
    viewer = ViserViewer(host, port) if viewer_name == "viser" else MeshcatViewer(host, port)
    return DemoApp(simulation, viewer, render, nerf_options)


class _TerminalProgress:
    """A rich progress bar for the start-up, called as ``progress(stage, fraction)``."""

    def __enter__(self):
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

        self.bar = Progress(
            BarColumn(), TaskProgressColumn(), TimeElapsedColumn(), TextColumn("{task.description}"), transient=True
        )
        self.task = self.bar.add_task("starting", total=1.0)
        self.bar.start()
        return self

    def __call__(self, stage: str, fraction: float) -> None:
        self.bar.update(self.task, completed=fraction, description=stage)

    def __exit__(self, *exc) -> None:
        self.bar.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scene",
        default="plant",
        help="plant, teapot, jelly, cloth, sculpture, a mesh path or a NeRF checkpoint (.pt)",
    )
    parser.add_argument("--device", choices=list(backend.DEVICES), default=None)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--viewer", choices=("meshcat", "viser"), default="meshcat")
    parser.add_argument("--smoke", action="store_true", help="start, run a few steps headless, exit")
    parser.add_argument(
        "--render",
        choices=RENDER_MODES,
        default="mesh",
        help="what the page shows first (the panel switches it): browser mesh, particles, or the "
        "server's warped-NeRF image (trains the scene's NeRF on first use)",
    )
    parser.add_argument("--nerf-checkpoint", default=None, help="a trained NeRF checkpoint to render instead")
    parser.add_argument("--cache-dir", default=None, help="cache of scene renders and NeRF checkpoints")
    args = parser.parse_args(argv)
    backend.init(args.device)
    try:
        with _TerminalProgress() as progress:
            app = build_app(
                args.scene,
                args.viewer,
                args.host,
                args.port,
                args.smoke,
                args.render,
                args.nerf_checkpoint,
                args.cache_dir,
                progress,
            )
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.smoke:
        app.run(steps=3)
        app.viewer.close()
        print(f"smoke: 3 steps of {args.scene}, t = {app.simulation.time:.3f} s")
        if args.render != "mesh":
            from pienerf.session import orbit_cameras

            sim = app.simulation
            cameras = orbit_cameras(sim.centre, 2.6, [30.0], 15.0, 64, 48)
            frame = sim.render(cameras, 0, "nerf" if args.render == "nerf" else "particles")
            coverage = float((frame.rgba[..., 3] > 0.5).float().mean())
            print(f"smoke: {args.render} frame 64x48, {100 * coverage:.0f} % covered")
        return 0
    url = getattr(app.viewer, "url", None) or f"http://{args.host}:{app.viewer.port}"
    print(f"viewer at {url}; Ctrl+C stops")
    try:
        app.run()
    except KeyboardInterrupt:
        pass
    finally:
        app.viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
