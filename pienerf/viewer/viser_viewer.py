"""The viser front end of the interactive viewer: the scene, a controls panel and mouse dragging in a browser.

The page shows the deformed scene mesh (updated every frame), the particles and the integrator points as toggles,
and a panel with the material (Young's modulus, Poisson ratio, density, model), damping, gravity, the kernel count
(re-sampling shows progress), reset / pin / push / cut / release buttons, the frame rate and the time breakdown.
The press of a mouse drag picks a material point and the pointer, on the camera-aligned plane through it, is the
drag target until release. A click picks too; a further click moves the target onto that ray at the picked depth,
and the gizmo at the target moves it in 3-D. In the ``"nerf"`` render mode each client gets the warped NeRF
rendered from its own camera as the page's background image with its depth, coarse while things move and refined
once still (:class:`pienerf.preview.RefinementSchedule`).

Every event becomes a command of the :class:`pienerf.viewer.loop.DemoApp`; this module holds no simulation logic.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pienerf.cameras import viser_cameras
from pienerf.preview import RefinementSchedule
from pienerf.viewer.loop import RENDER_MODES, DemoApp, load_nerf, vector3

__all__ = ["ViserViewer"]


class ViserViewer:
    """The browser viewer: a viser server with the scene, the controls panel and click-to-drag.

    Args:
        host, port: where the page is served.
        nerf_height: height in pixels of the NeRF images rendered for each client (width from its aspect).
        background: colour behind the NeRF render, RGB in [0, 1].
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, nerf_height: int = 240, background=(1.0, 1.0, 1.0)):
        import viser  # deferred: the optional browser viewer

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
        # viser's mesh takes one colour (the scene's median); its only vertex-coloured path, a GLB, is re-sent and
        # re-parsed whole on every change, where this mesh takes each frame's vertex buffer alone.
        self.mesh = server.scene.add_mesh_simple(
            "/body", sim.deformed_mesh_vertices().numpy(), faces, color=tuple(np.median(self._colors, 0).astype(int))
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
            self.model = gui.add_dropdown("model", sim.material_models, initial_value=material.model)
            self.damping = gui.add_slider("damping α (1/s)", 0.0, 20.0, 0.5, sim.config.solver.rayleigh_alpha)
            self.gravity = gui.add_slider("gravity (m/s²)", 0.0, 20.0, 0.1, -sim.config.solver.gravity[1])
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
        self.pin.on_click(lambda _e: app.submit("pin", sim.pin_picked))
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
            origin, direction = vector3(event.ray_origin, "ray origin"), vector3(event.ray_direction, "ray direction")
        except ValueError as error:
            self.report(f"ignored a malformed click: {error}")
            return
        self.app.submit("click", lambda: self.app.click(origin, direction))

    def _on_drag(self, event) -> None:
        """A mouse drag on the mesh: pick under the press, follow the pointer on the camera-aligned plane
        through the picked point, let go at release."""
        try:
            if event.phase == "start":
                origin = vector3(event.client.camera.position, "camera position")
                direction = vector3(event.start_position, "drag start") - origin
                self.app.submit("drag start", lambda: self.app.simulation.pick(origin, direction))
            elif event.phase == "update":
                target = vector3(event.end_position, "drag position")
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
            z = cameras.axial_depth(0, frame.depth.cpu())  # viser composites by depth along the optical axis
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
        self.app.simulation.push_picked()
        self._remove_gizmo()

    def _remove_gizmo(self) -> None:
        if self._gizmo is not None:
            self._gizmo.remove()
            self._gizmo = None

    def _sync_gizmo(self) -> None:
        target = self.app.simulation.drag_target
        if target is None:
            self._remove_gizmo()
            return
        target = target.numpy()
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
