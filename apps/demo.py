"""Interactive drag-and-force viewer of a Q-GMLS body (PIE-NeRF Fig. 1, 5).

    python -m apps.demo [--scene plant|teapot|jelly|cloth|sculpture|PATH] [--device cpu|cuda]
                        [--host 127.0.0.1] [--port 8080] [--viewer viser|meshcat] [--smoke]

``viser`` (default) serves a page: the deformed scene mesh (updated every frame), the particles and the
integrator points as toggles, and a panel with the material (Young's modulus, Poisson ratio, density, model),
damping, gravity, the kernel count (re-sampling shows progress), reset / pin / push / cut / release buttons, the
frame rate and the time breakdown. Drag the body with the mouse: the press picks a material point and the
pointer, on the camera-aligned plane through it, is the drag target until release. A click picks too; a further
click moves the target onto that ray at the picked depth, and the gizmo at the target moves it in 3-D. The spring of
:class:`pienerf.picking.DragController` pulls the body. ``meshcat`` is display-only (meshcat cannot send input
back): it streams the simulation under a scripted sweeping drag. ``--smoke`` starts the viewer, runs a few steps
headless and exits 0.

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

SMOKE = {"kernel_count": 6, "particle_radius": 0.06, "lloyd_iterations": 0}


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
    """

    def __init__(self, simulation, viewer: Viewer):
        self.simulation = simulation
        self.viewer = viewer
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
    """The browser viewer: a viser server with the scene, the controls panel and click-to-drag."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080):
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.app: DemoApp | None = None
        self._gizmo = None
        self._gizmo_sync = False

    # -- construction ----------------------------------------------------------------------------

    def attach(self, app: DemoApp) -> None:
        self.app = app
        server, sim = self.server, app.simulation
        server.scene.set_up_direction("+y")
        faces = sim.mesh_faces.numpy().astype(np.uint32)
        self._faces = faces
        self._colors = (sim.mesh_colors.numpy() * 255).astype(np.uint8)
        self.mesh = server.scene.add_mesh_simple("/body", sim.deformed_mesh_vertices().numpy(), faces,
                                                 color=(200, 170, 120))
        self.particles = server.scene.add_point_cloud(
            "/particles", sim.particle_positions().numpy(), (sim.particle_colors.numpy() * 255).astype(np.uint8),
            point_size=0.6 * sim.particle_radius, visible=False)
        self.ips = server.scene.add_point_cloud("/integrator_points", sim.integrator_positions().numpy(),
                                                (230, 40, 40), point_size=1.2 * sim.particle_radius, visible=False)
        server.scene.add_grid("/ground", width=4.0, height=4.0, plane="xz", position=(0.0, 0.0, 0.0))
        self._build_gui(app)
        server.scene.on_click()(self._on_click)
        self.mesh.on_drag("left")(self._on_drag)
        server.on_client_connect(self._on_connect)

    def _build_gui(self, app: DemoApp) -> None:
        gui, sim = self.server.gui, app.simulation
        material = sim.material
        with gui.add_folder("Material"):
            self.young = gui.add_slider("Young's modulus log10(Pa)", 3.0, 7.0, 0.1, math.log10(material.young_modulus))
            self.poisson = gui.add_slider("Poisson ratio", 0.0, 0.49, 0.01, material.poisson_ratio)
            self.density = gui.add_slider("density (kg/m³)", 100.0, 3000.0, 50.0, material.density)
            self.model = gui.add_dropdown("model", ("neo_hookean", "arap", "stvk", "fixed_corotated"),
                                          initial_value=material.model)
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
            self.show_mesh = gui.add_checkbox("mesh", True)
            self.show_particles = gui.add_checkbox("particles", False)
            self.show_ips = gui.add_checkbox("kernels and integrator points", False)
        self.stats = gui.add_markdown("starting")
        self.message = gui.add_markdown("click the body to pick, click again to drag")

        def material_changed(_event) -> None:
            values = dict(young_modulus=10.0 ** self.young.value, poisson_ratio=self.poisson.value,
                          density=self.density.value, model=self.model.value, damping=self.damping.value,
                          gravity=(0.0, -self.gravity.value, 0.0))
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
            self._gizmo = self.server.scene.add_transform_controls("/drag_target", scale=0.2, disable_rotations=True,
                                                                   position=target)

            def moved(_event, gizmo=self._gizmo) -> None:
                position = np.asarray(gizmo.position, dtype=np.float64)
                self.app.submit("gizmo drag", lambda: self.app.simulation.drag_to(target=position))

            self._gizmo.on_update(moved)
        elif not np.allclose(self._gizmo.position, target):
            self._gizmo.position = target

    # -- per frame -------------------------------------------------------------------------------

    def update(self, app: DemoApp) -> None:
        sim = app.simulation
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


class MeshcatViewer:
    """Display-only viewer through meshcat: the deformed mesh streamed every frame."""

    def __init__(self, zmq_url: str | None = None):
        import meshcat

        self.vis = meshcat.Visualizer(zmq_url=zmq_url)
        self.url = self.vis.url()

    def attach(self, app: DemoApp) -> None:
        self.app = app

    def update(self, app: DemoApp) -> None:
        import meshcat.geometry as g

        sim = app.simulation
        vertices = sim.deformed_mesh_vertices().numpy()
        colors = sim.mesh_colors.numpy()
        geometry = g.TriangularMeshGeometry(vertices, sim.mesh_faces.numpy(), color=colors)
        self.vis["body"].set_object(geometry, g.MeshLambertMaterial(vertexColors=True))

    def report(self, message: str) -> None:
        print(message, file=sys.stderr)

    def close(self) -> None:
        self.vis.delete()


def sweeping_drag(simulation, amplitude: float = 0.15, period: float = 2.0) -> Callable[[float], torch.Tensor]:
    """A scripted mouse: grab the particle highest above the pins and sweep it sideways, sinusoidally (m, s)."""
    position = simulation.model.position
    top = int(position[:, 1].argmax())
    simulation.interaction.drag.grab(position[top], simulation.state.q)
    rest = position[top].double().cpu()

    def target(t: float) -> torch.Tensor:
        return rest + torch.tensor([amplitude * math.sin(2.0 * math.pi * t / period), 0.0, 0.0],
                                   dtype=torch.float64)

    return target


def build_app(scene: str, viewer_name: str, host: str, port: int, smoke: bool) -> DemoApp:
    """The simulation of ``scene`` behind the chosen viewer."""
    from pienerf.session import Simulation, SimulationConfig

    simulation = Simulation(SimulationConfig(scene=scene, **(SMOKE if smoke else {})))
    if viewer_name == "viser":
        viewer = ViserViewer(host, port)
        app = DemoApp(simulation, viewer)
    else:
        viewer = MeshcatViewer()
        app = DemoApp(simulation, viewer)
        app.scripted_drag = sweeping_drag(simulation)
    return app


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="plant", help="plant, teapot, jelly, cloth, sculpture or a mesh path")
    parser.add_argument("--device", choices=list(backend.DEVICES), default=None)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--viewer", choices=("viser", "meshcat"), default="viser")
    parser.add_argument("--smoke", action="store_true", help="start, run a few steps headless, exit")
    args = parser.parse_args(argv)
    backend.init(args.device)
    try:
        app = build_app(args.scene, args.viewer, args.host, args.port, args.smoke)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.smoke:
        app.run(steps=3)
        app.viewer.close()
        print(f"smoke: 3 steps of {args.scene}, t = {app.simulation.time:.3f} s")
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
