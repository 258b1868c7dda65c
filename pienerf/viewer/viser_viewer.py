"""The viser front end of the interactive viewer: the scene, a controls panel and mouse dragging in a browser.

The page shows the deformed scene mesh (updated every frame), the particles and the integrator points as toggles,
and a panel with the material (Young's modulus, Poisson ratio, density, model), damping, gravity, the kernel count
(re-sampling shows progress), reset / pin / push / cut / release buttons, the frame rate and the time breakdown.
The press of a mouse drag picks a material point and the pointer, on the camera-aligned plane through it, is the
drag target until release. A click picks too; a further click moves the target onto that ray at the picked depth,
and the gizmo at the target moves it in 3-D. In the ``"nerf"`` render mode each client gets the warped NeRF
rendered from its own camera as the page's background image with its depth, while things move as coarse as the
frame budget asks, refined once still (:class:`pienerf.render.RefinementSchedule`).

A "scene" menu at the top of the panel switches the scene (:meth:`pienerf.viewer.loop.DemoApp.switch_scene`): the
chosen scene is built (progress in the panel), then the scene and the panel are emptied and built again for it; a
build that fails leaves the current scene, with the error in the panel. In a garment scene (the dressed avatar) the
garment's faces that have a vertex within the barrier's reach of the body show in the contact colour, the rest in
the garment's, and the panel counts the contact.

Every event becomes a command of the :class:`pienerf.viewer.loop.DemoApp`; this module holds no simulation logic.
Every value from the page is range-checked as it arrives (:func:`pienerf.viewer.loop.control_value`); a bad one is
refused with a message at the top of the panel and the control goes back to the value in use. Switching to the NeRF
the first time fits it in a separate process while the simulation goes on (:class:`pienerf.viewer.loop.NerfJob`).

Security: the page and its websocket are served on the viewer's address by viser's own server, into which
:func:`pienerf.viewer.origin.checked_viser_server` puts the viewer's :class:`~pienerf.viewer.origin.RequestCheck`:
foreign ``Host`` headers (DNS rebinding) and cross-origin requests are refused before viser answers, and the viewer
listens on that one port only. A malformed message closes that client's connection (viser's behaviour) and is logged
as one line, at most one every few seconds, instead of a traceback.
"""

from __future__ import annotations

import contextlib
import io
import logging
import time

import numpy as np
import torch

from pienerf.nerf.cameras import viser_cameras
from pienerf.viewer.loop import (
    CONTROL_RANGES,
    RENDER_MODES,
    DemoApp,
    NerfSchedules,
    control_value,
    nerf_image,
    si_text,
    vector3,
)
from pienerf.viewer.origin import check_address, checked_viser_server

__all__ = ["ViserViewer"]

_LOG = logging.getLogger(__name__)
_WARNING_INTERVAL = 5.0  # s between two log lines about malformed messages


class _MalformedMessageLog(logging.Filter):
    """Turns the tracebacks logged when viser fails on a malformed message into one line, at most one every few
    seconds (counting those in between).

    viser fails in two places: a message that does not decode ends the client's connection handler, which
    ``websockets`` logs ("connection handler failed", matched to this server by its port); a message that decodes
    but carries a value of the wrong type (text for a number) fails in a task of viser's event loop, which
    ``asyncio`` logs when the task is freed ("Task exception was never retrieved", matched by viser's handler).
    """

    def __init__(self, port: int):
        super().__init__()
        self.port = port
        self.count = 0
        self._unreported = 0
        self._last = -float("inf")

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == "asyncio":
            if "WebsockMessageHandler._handle_incoming_message" not in str(record.msg):
                return True
            who, what = "a viser client", "dropped a malformed message"
        else:
            connection = getattr(record, "websocket", None)
            address = getattr(connection, "local_address", None)
            if record.msg != "connection handler failed" or not address or address[1] != self.port:
                return True
            who, what = f"viser client {getattr(connection, 'remote_address', '?')}", "closed after a malformed message"
        error = record.exc_info[1] if record.exc_info else None
        self.count += 1
        self._unreported += 1
        now = time.monotonic()
        if now - self._last < _WARNING_INTERVAL:
            return False
        record.msg = "%s: %s (%d since the last report; last: %s)"
        record.args = (who, what, self._unreported, f"{type(error).__name__}: {error}"[:200])
        record.exc_info, record.exc_text, record.levelno, record.levelname = None, None, logging.WARNING, "WARNING"
        self._last, self._unreported = now, 0
        return True


class ViserViewer:
    """The browser viewer: a viser server with the scene, the controls panel and click-to-drag.

    Args:
        host, port: where the page is served (port 0 picks a free one, see :attr:`port`); a bad address raises
            ValueError, a port in use OSError, both naming the fix.
        nerf_height: height in pixels of the NeRF images rendered for each client (width from its aspect).
        background: colour behind the NeRF render, RGB in [0, 1].
        frame_budget: seconds a frame of the NeRF mode may take while things move, step and render together; the
            render's resolution adapts to hold it (:class:`pienerf.render.RefinementSchedule`); later through
            :attr:`nerf_schedules` (:class:`pienerf.viewer.loop.NerfSchedules`).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        nerf_height: int = 240,
        background=(1.0, 1.0, 1.0),
        frame_budget: float = 1.0 / 30.0,
    ):
        check_address(host, port)
        self.nerf_schedules = NerfSchedules(frame_budget)  # checks the budget before the server starts
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its address; the app prints the page's
            self.server, self.request_check = checked_viser_server(host, port)
        self.port = self.server.get_port()
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        self.malformed_log = _MalformedMessageLog(self.port)
        for name in ("websockets.server", "asyncio"):
            logging.getLogger(name).addFilter(self.malformed_log)
        self.app: DemoApp | None = None
        self._gizmo = None
        self._gizmo_sync = False
        self._setting = False  # the viewer is setting a GUI value itself
        self.nerf_height = int(nerf_height)
        self.background = torch.tensor(background, dtype=torch.float32)
        self.nerf_renders: list[int] = []  # downscale of every NeRF image sent, in order
        self.last_nerf_image: np.ndarray | None = None  # [H, W, 3] uint8, the latest one
        self._garment = False  # a garment scene (the dressed avatar) is shown
        self._events = False  # the scene's click and the clients' connect are handled (once, across scenes)
        self._near: np.ndarray | None = None  # [V] bool, the garment vertices tinted last

    # -- construction ----------------------------------------------------------------------------

    def attach(self, app: DemoApp) -> None:
        """Build the scene and the panel of ``app``'s simulation (again after :meth:`detach`)."""
        self.app = app
        server, sim = self.server, app.simulation
        server.scene.set_up_direction("+y")
        if not self._events:
            self._events = True
            server.scene.on_click()(self.on_click)
            server.on_client_connect(self._on_connect)
        if getattr(sim, "kind", "body") == "garment":
            self._attach_garment(app)
            return
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
        self.mesh.on_drag("left")(self._on_drag)
        self._show(app.render_mode)

    def _build_gui(self, app: DemoApp) -> None:
        gui, sim = self.server.gui, app.simulation
        material = sim.material
        # Status first, so the frame rate, the last message and the time breakdown show without scrolling.
        self.stats = gui.add_markdown("starting")
        self.message = gui.add_markdown("click the body to pick, click again to drag")
        self.breakdown = gui.add_markdown("")
        self._accepted = {}
        self._add_scene_menu(app)
        with gui.add_folder("Material"):
            lo, hi = CONTROL_RANGES["young_modulus"]
            self.young = gui.add_number("Young's modulus (Pa)", material.young_modulus, min=lo, max=hi, step=1.0)
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
        self._accepted.update({id(handle): handle.value for handle in self._material_handles})
        for handle in self._material_handles:
            handle.on_update(self._refusing(handle, self._material_changed))
        self.resample.on_click(self._refusing(None, self._resample_clicked))
        self.release.on_click(lambda _e: app.submit("release", sim.release))
        self.pin.on_click(lambda _e: app.submit("pin", sim.pin_picked))
        self.push.on_click(lambda _e: app.submit("force", sim.push_picked))
        self.cut.on_click(lambda _e: app.submit("cut", lambda: sim.cut_picked((0.0, 1.0, 0.0)), heavy=True))
        self.reset.on_click(lambda _e: app.submit("reset", sim.reset, key="reset"))
        self.show_mesh.on_update(lambda _e: setattr(self.mesh, "visible", self.show_mesh.value))
        self.show_particles.on_update(lambda _e: setattr(self.particles, "visible", self.show_particles.value))
        self.show_ips.on_update(lambda _e: setattr(self.ips, "visible", self.show_ips.value))
        self._accepted[id(self.render_mode)] = self.render_mode.value
        self.render_mode.on_update(self._refusing(self.render_mode, self._render_mode_chosen))

    def _add_scene_menu(self, app: DemoApp) -> None:
        """The scene menu (when ``app`` offers scenes): a choice is checked and queued, a bad one refused."""
        self.scene_menu = None
        if not app.scenes:
            return
        self.scene_menu = self.server.gui.add_dropdown("scene", app.scenes, initial_value=app.scene)
        self._accepted[id(self.scene_menu)] = app.scene
        self.scene_menu.on_update(self._refusing(self.scene_menu, app.choose_scene))

    def detach(self) -> None:
        """Empty the scene and the panel (a scene switch builds them again for the next scene)."""
        self._remove_gizmo()
        self.server.scene.set_background_image(None)
        self.server.scene.reset()
        self.server.gui.reset()
        self._garment, self._near = False, None
        self.nerf_schedules.drop()

    def _set_quietly(self, handle, value) -> None:
        """Show ``value`` in ``handle`` (and accept it) without running its callback."""
        self._setting = True
        try:
            handle.value = self._accepted[id(handle)] = value
        finally:
            self._setting = False

    @property
    def _material_handles(self) -> tuple:
        return (self.young, self.poisson, self.density, self.model, self.damping, self.gravity)

    def _refusing(self, handle, translate):
        """A GUI callback that runs ``translate(value)``; a bad value is refused with a message in the panel and
        ``handle`` goes back to the value last accepted."""

        def callback(_event) -> None:
            if self._setting:  # the viewer itself set the value (a revert): nothing to translate
                return
            try:
                translate(None if handle is None else handle.value)
            except Exception as error:  # any bad value: say so, keep what is in use
                self.report(f"refused: {error}")
                if handle is not None and id(handle) in self._accepted:
                    self._set_quietly(handle, self._accepted[id(handle)])
                return
            if handle is not None:
                self._accepted[id(handle)] = handle.value

        return callback

    def _material_changed(self, _value) -> None:
        models = self.app.simulation.material_models
        if self.model.value not in models:
            raise ValueError(f"unknown material model {str(self.model.value)[:40]!r}; valid: {', '.join(models)}")
        values = dict(
            young_modulus=control_value("young_modulus", self.young.value),
            poisson_ratio=control_value("poisson_ratio", self.poisson.value),
            density=control_value("density", self.density.value),
            model=self.model.value,
            damping=control_value("damping", self.damping.value),
            gravity=(0.0, -control_value("gravity", self.gravity.value), 0.0),
        )
        self.app.submit(
            "material change",
            lambda: self.app.simulation.set_material(**values),
            key="material change",
            report=lambda m: f"E = {si_text(m.young_modulus, 'Pa')}, ν = {m.poisson_ratio:.3g} ({m.model})",
        )

    def _resample_clicked(self, _value) -> None:
        count = int(control_value("kernel_count", self.kernels.value))
        sim = self.app.simulation
        progress = lambda stage, fraction: self.show_progress(f"resampling: {stage}", fraction)  # noqa: E731
        self.app.submit("resample", lambda: sim.resample(count, progress), key="resample", heavy=True)

    def _render_mode_chosen(self, mode) -> None:
        if mode not in RENDER_MODES:
            raise ValueError(f"unknown render mode {str(mode)[:40]!r}; valid: {', '.join(RENDER_MODES)}")
        self.app.submit("render mode", lambda: self.set_render_mode(mode), key="render mode")

    # -- a garment scene -------------------------------------------------------------------------

    def _attach_garment(self, app: DemoApp) -> None:
        """The garment (dragged like a body), the mannequin and the garment panel: motion, playback, fabric.

        viser's simple mesh takes one colour, and its vertex-coloured path (a GLB) is re-sent whole on every change,
        so the garment is two simple meshes over the same vertex buffer: its faces with no vertex near the body in
        the garment's colour, and those with one (:meth:`_tint`) in the contact colour; the faces move between them
        when the contact changes, the vertices go to both every frame."""
        self._garment = True
        server, sim, gui = self.server, app.simulation, self.server.gui
        vertices, faces = sim.deformed_mesh_vertices().numpy(), sim.mesh_faces.numpy().astype(np.uint32)
        colors = (sim.vertex_colors().numpy() * 255).round().astype(np.uint8)
        near = sim.near_body().numpy()
        self._garment_faces = faces
        self.mesh = server.scene.add_mesh_simple("/body", vertices, faces, color=(204, 56, 51), side="double")
        self.tinted = server.scene.add_mesh_simple("/body_contact", vertices, faces[:1], color=(255, 217, 26),
                                                   side="double", visible=False)  # fmt: skip
        self._tint(near, colors)
        self.avatar = server.scene.add_mesh_simple(
            "/avatar", sim.body_vertices().numpy(), sim.body_faces.numpy().astype(np.uint32), color=(199, 189, 173)
        )
        self.ground = server.scene.add_grid("/ground", width=4.0, height=4.0, plane="xz", position=(0.0, 0.0, 0.0))
        self.stats = gui.add_markdown("starting")
        self.message = gui.add_markdown("; ".join(sim.notes))
        self.breakdown = gui.add_markdown("")
        self.contact = gui.add_markdown("")
        self._accepted = {}
        self._add_scene_menu(app)
        fabric = sim.fabric
        with gui.add_folder("Garment"):
            self.motion = gui.add_dropdown("motion", sim.motions, initial_value=sim.motion)
            self.play = gui.add_button("play")
            self.pause = gui.add_button("pause")
            self.frame = gui.add_slider("frame", 0, sim.frame_count - 1, 1, 0)
            self.speed = gui.add_slider("speed (frames a step)", 0.0, 4.0, 0.25, sim.speed)
            self.preset = gui.add_dropdown("fabric", (*sim.fabric_presets, "custom"), initial_value=sim.fabric_name)
            self.fabric_density = gui.add_slider("density (kg/m³)", 200.0, 640.0, 10.0, fabric.density)
            self.kappa_s = gui.add_slider("κs", 0.1, 8.0, 0.1, fabric.kappa_s)
            self.kappa_b = gui.add_slider("κb", 0.1, 8.0, 0.1, fabric.kappa_b)
            self.friction = gui.add_slider("friction μ", 0.0, 1.0, 0.05, fabric.friction)
        with gui.add_folder("Interaction"):
            self.release = gui.add_button("release")
            self.pin = gui.add_button("pin picked vertex")
            self.reset = gui.add_button("reset")
        self.progress = gui.add_progress_bar(100.0, visible=False)
        fabric_handles = {"density": self.fabric_density, "kappa_s": self.kappa_s, "kappa_b": self.kappa_b,
                          "friction": self.friction}  # fmt: skip
        self._accepted.update({id(h): h.value for h in (self.motion, self.preset, *fabric_handles.values())})

        def fabric_changed(name):
            return lambda value: app.submit(
                name, lambda: (sim.set_fabric(**{name: value}), self._sync_fabric()), key=f"set {name}"
            )

        for name, handle in fabric_handles.items():
            handle.on_update(self._refusing(handle, fabric_changed(name)))

        def preset_chosen(name):
            if name != "custom":
                app.submit("preset", lambda: (sim.apply_preset(name), self._sync_fabric()), key="set preset")

        self.preset.on_update(self._refusing(self.preset, preset_chosen))
        self.motion.on_update(
            self._refusing(self.motion, lambda name: app.submit("motion", lambda: sim.set_motion(name)))
        )
        self.play.on_click(lambda _e: app.submit("play", sim.play, key="play"))
        self.pause.on_click(lambda _e: app.submit("pause", sim.pause, key="play"))
        self.frame.on_update(
            lambda _e: None if self._setting else app.submit("scrub", lambda: sim.scrub(self.frame.value))
        )
        self.speed.on_update(self._refusing(self.speed, lambda v: app.submit("speed", lambda: sim.set_speed(v))))
        self.release.on_click(lambda _e: app.submit("release", sim.release))
        self.pin.on_click(lambda _e: app.submit("pin", sim.pin_picked))
        self.reset.on_click(lambda _e: app.submit("reset", sim.reset, key="reset"))
        self.mesh.on_drag("left")(self._on_drag)
        self.tinted.on_drag("left")(self._on_drag)

    def _sync_fabric(self) -> None:
        """The fabric sliders and menu show the fabric in use (after a preset or a refused value)."""
        sim = self.app.simulation
        fabric = sim.fabric
        values = (
            (self.fabric_density, fabric.density),
            (self.kappa_s, fabric.kappa_s),
            (self.kappa_b, fabric.kappa_b),
            (self.friction, fabric.friction),
            (self.preset, sim.fabric_name),
        )
        for handle, value in values:
            if handle.value != value:
                self._set_quietly(handle, value)

    def _tint(self, near: np.ndarray, colors: np.ndarray) -> None:
        """Show the garment's faces that have a vertex in ``near`` (``[V]`` bool) in that vertex's colour of
        ``colors`` (``[V, 3]`` uint8), the others in the garment's colour; nothing is sent when ``near`` is as
        last shown."""
        if self._near is not None and np.array_equal(near, self._near):
            return
        self._near = near
        faces = self._garment_faces
        touching = near[faces].any(1)
        if touching.any():
            self.tinted.faces = faces[touching]
            self.tinted.color = tuple(int(c) for c in colors[near][0])
        self.tinted.visible = bool(touching.any())
        # an empty face list draws nothing in either mesh: the hidden mesh keeps its last faces
        if not touching.all():
            self.mesh.faces = faces[~touching]
        self.mesh.visible = not touching.all()

    def _update_garment(self, app: DemoApp) -> None:
        sim = app.simulation
        with self.server.atomic():
            vertices = sim.deformed_mesh_vertices().numpy()
            self.mesh.vertices = self.tinted.vertices = vertices
            self.avatar.vertices = sim.body_vertices().numpy()
            self._tint(sim.near_body().numpy(), (sim.vertex_colors().numpy() * 255).round().astype(np.uint8))
        self._sync_gizmo()
        contact = sim.contact()
        seconds = sim.time_breakdown()["seconds_per_step"]
        self.stats.content = (
            f"**{app.fps:.1f} fps**, t = {sim.time:.2f} s, {sim.motion} frame {sim.frame:.0f}"
            f"{'' if sim.playing else ' (paused)'}, {sim.last_report.newton_iterations} Newton iterations"
        )
        self.breakdown.content = ", ".join(f"{name} {1e3 * value:.1f} ms" for name, value in seconds.items())
        body, own = contact["min_body_m"], contact["min_self_m"]
        self.contact.content = (
            f"contact: {contact['near']} vertices within d̂ = {1e3 * contact['reach_m']:g} mm (tinted), "
            "min distance to body "
            f"{f'{1e3 * body:.2f} mm' if np.isfinite(body) else 'far'}, to itself "
            f"{f'{1e3 * own:.2f} mm' if np.isfinite(own) else '> d̂'}, {contact['inside']} vertices inside the body"
        )

    # -- events ----------------------------------------------------------------------------------

    def on_click(self, event) -> None:
        """A click in the scene (viser's event: ``ray_origin``, ``ray_direction``): pick along its ray."""
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
                self.app.submit("drag", lambda: self.app.simulation.drag_to(target=target), key="drag")
            else:
                self.app.submit("drag end", self.app.simulation.release)
        except ValueError as error:
            self.report(f"ignored a malformed drag: {error}")

    def _on_connect(self, client) -> None:
        sim = self.app.simulation
        centre = sim.centre.double().numpy()
        client.camera.up_direction = (0.0, 1.0, 0.0)
        client.camera.position = centre + np.array([0.0, 0.3, 2.6])
        client.camera.look_at = centre
        client.camera.on_update(lambda _camera: self.app.wake())  # a still NeRF view is rendered again
        self.app.wake()  # a loop asleep for want of a client runs again

    def has_clients(self) -> bool:
        """Whether a client is connected."""
        return bool(self.server.get_clients())

    def set_render_mode(self, mode: str) -> None:
        """Switch what the page shows; the first time, the NeRF is fitted in the background (progress in the
        panel) and shown once ready, while the simulation goes on."""
        app = self.app
        if mode == "nerf" and "nerf" not in app.simulation.render_backends:
            self._set_quietly(self.render_mode, app.render_mode)  # until it is ready
            app.fit_nerf(lambda: self.set_render_mode("nerf"))
            return
        app.render_mode = mode
        self._set_quietly(self.render_mode, mode)
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
        self.nerf_schedules.drop()

    def _update_nerf(self, app: DemoApp) -> None:
        """Render the warped NeRF from every client's camera: as coarse as the frame budget asks while things move,
        refined when still."""
        sim = app.simulation
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
            schedule = self.nerf_schedules.of(client_id)
            level = schedule.next(sim.state.q, view)
            if level is None:
                continue
            cameras = viser_cameras(camera.position, camera.wxyz, camera.fov, camera.aspect, self.nerf_height)
            image, frame = nerf_image(app, schedule, cameras, level, self.background)
            z = cameras.axial_depth(0, frame.depth.cpu())  # viser composites by depth along the optical axis
            z = torch.where(torch.isfinite(z), z, 100.0)
            client.scene.set_background_image(image, format="jpeg", depth=z.numpy())
            self.nerf_renders.append(level)
            self.last_nerf_image = image

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
        if self._garment:
            self._update_garment(app)
            return
        if app.render_mode == "nerf" and "nerf" in sim.render_backends:
            self._update_nerf(app)
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
            f"{report.iterations} Newton iterations"
        )
        self.breakdown.content = ", ".join(f"{name} {1e3 * value:.1f} ms" for name, value in seconds.items())

    def report(self, message: str) -> None:
        self.message.content = message

    def show_progress(self, stage: str, fraction: float | None) -> None:
        """The progress bar under the kernel count, and the stage as the panel's message (hidden with ``None``)."""
        self.progress.visible = fraction is not None
        if fraction is not None:
            self.progress.value = 100.0 * min(max(float(fraction), 0.0), 1.0)
            self.report(stage)

    def close(self) -> None:
        self.server.stop()
        for name in ("websockets.server", "asyncio"):
            logging.getLogger(name).removeFilter(self.malformed_log)
