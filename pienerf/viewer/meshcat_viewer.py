"""The meshcat front end of the interactive demo: translates the page's events into :class:`Simulation` verbs.

The scene goes to meshcat's three.js client as meshcat commands under one root node, ``/pienerf``, that turns the
scene's y-up coordinates into meshcat's z-up world (a rotation of +90° about x); the page's script sends pointer
rays and its camera back in the scene's coordinates. Every frame sends only vertex buffers (the script's
``set_vertices``), the drag marker's transform and a status line; the scene and the controls are built once.
meshcat's own commands offer no cheaper path: its ``set_property`` assigns fields of the scene node's object and
cannot reach a geometry's attribute buffer, and a ``set_object`` per frame would parse and rebuild the geometry,
its material and its folder of meshcat's scene panel.

Page messages (JSON objects; anything else is dropped and counted by :class:`MeshcatServer`):

- ``{"type": "pick", "origin", "direction"}``: the ray (m, scene axes) under a press on the body; picks a point
  and starts a drag.
- ``{"type": "drag", "origin", "direction"}``: the pointer's ray while pressed; moves the drag target along it.
- ``{"type": "release"}``: let go of the picked point.
- ``{"type": "pin" | "push" | "cut" | "reset"}``: the buttons; pin / constant force at / cut through the picked
  point, back to rest.
- ``{"type": "set", "name", "value"}``: a control; ``young_modulus`` (Pa), ``poisson_ratio``, ``density``
  (kg/m³), ``damping`` (1/s), ``gravity`` (m/s², its magnitude along -y), ``model``, ``render_mode``.
- ``{"type": "resample", "kernel_count"}``: re-discretise with that many kernels (progress in the page).
- ``{"type": "camera", "matrix", "fov", "aspect"}``: the page's camera; camera-to-world ``[16]`` (column-major,
  scene axes, OpenGL camera axes), vertical field of view (degrees), width over height. The NeRF mode renders
  from it.
- ``{"type": "play" | "pause"}``: play or hold a garment scene's motion; in a body scene, run or pause the loop.
- ``{"type": "scene", "name"}``: the scene menu; builds that scene (progress in the page) and shows it in place of
  the current one, which stays when the build fails (:meth:`pienerf.viewer.loop.DemoApp.switch_scene`).

A garment scene (a simulation whose ``kind`` is ``"garment"``: the dressed avatar, :class:`physavatar.session.
AvatarSimulation`) shows the garment as the pickable body, the mannequin beside it, and the garment panel; its
``set`` names are :data:`GARMENT_CONTROLS`, ``motion`` and ``preset``. Garment vertices within the barrier's reach of
the body are tinted (the script's ``set_colors``, sent when the tint changes).

A scene switch deletes the root node in every tab, forgets what the server replays to tabs that open later
(:meth:`pienerf.viewer.meshcat_server.MeshcatServer.forget_all`) and builds the next scene as at the start.
"""

from __future__ import annotations

import base64
import io
import math
import sys
import threading

import meshcat.geometry as g
import numpy as np
import torch
import umsgpack
from meshcat.commands import Delete, SetObject, SetProperty, SetTransform
from meshcat.path import Path
from PIL import Image

from pienerf.nerf.cameras import Cameras, pinhole_camera
from pienerf.viewer.loop import (
    CONTROL_RANGES,
    RENDER_MODES,
    NerfSchedules,
    control_value,
    nerf_image,
    number_in,
    picked_text,
    si_text,
    vector3,
)
from pienerf.viewer.meshcat_server import MeshcatServer

__all__ = ["GARMENT_CONTROLS", "Y_UP_TO_Z_UP", "MeshcatViewer", "page_cameras"]

Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""``[4, 4]`` transform of the root node: the scene's y-up axes into meshcat's z-up world (+90° about x)."""

_ROOT = ("pienerf",)
_BODY = Path((*_ROOT, "body"))
_PARTICLES = Path((*_ROOT, "particles"))
_TARGET = Path((*_ROOT, "drag_target"))
_AVATAR = Path((*_ROOT, "avatar"))
_CONTROLS = tuple(name for name in CONTROL_RANGES if name != "kernel_count")
_BUTTONS = ("release", "pin", "push", "cut", "reset", "play", "pause")
_TYPES = ("pick", "drag", "camera", "set", "resample", "scene", *_BUTTONS)

GARMENT_CONTROLS = {
    "fabric_density": ("density", (200.0, 640.0)),
    "kappa_s": ("kappa_s", (0.1, 8.0)),
    "kappa_b": ("kappa_b", (0.1, 8.0)),
    "friction": ("friction", (0.0, 1.0)),
}
"""A garment scene's fabric sliders, page name -> (``set_fabric`` keyword, (lowest, highest)): density (kg/m³),
κ_s, κ_b and friction μ; ``speed`` (motion frames a step, 0–4) and ``frame`` (scrub) are its playback sliders."""
_GARMENT_ONLY = ("push", "cut", "resample")


def page_cameras(matrix, fov: float, aspect: float, height: int) -> Cameras:
    """:class:`Cameras` (one view) of the page's camera, ``height`` pixels high.

    Args:
        matrix: ``[16]`` camera-to-world transform, column-major as three.js stores it, in the scene's axes (m);
            the camera looks along its -z with y up (OpenGL axes, as :class:`Cameras`).
        fov: vertical field of view (degrees).
        aspect: width over height.
        height: image height (pixels).
    """
    try:
        c2w = np.asarray(matrix, dtype=np.float64).reshape(4, 4).T
    except (TypeError, ValueError):
        raise ValueError(f"camera matrix must be 16 numbers, got {str(matrix)[:80]}") from None
    if not np.isfinite(c2w).all() or not np.allclose(c2w[3], (0.0, 0.0, 0.0, 1.0)):
        raise ValueError("camera matrix must be a finite rigid transform (last row 0 0 0 1)")
    if not np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-3):
        raise ValueError("camera matrix must have an orthonormal rotation (no scale)")
    fov = number_in(fov, "camera fov (deg)", 1.0, 179.0)
    aspect = number_in(aspect, "camera aspect", 0.05, 20.0)
    return pinhole_camera(c2w, math.radians(fov), aspect, max(1, int(height)))


def _is_garment(simulation) -> bool:
    """Whether ``simulation`` is a garment scene (``kind == "garment"``) rather than a PIE-NeRF body."""
    return getattr(simulation, "kind", "body") == "garment"


def _colors_command(path: Path, colors: np.ndarray) -> dict:
    """The project script's ``set_colors``: a new ``[N, 3]`` float32 vertex-colour buffer for the geometry at
    ``path``."""
    data = np.ascontiguousarray(colors, dtype=np.float32)
    return {"type": "set_colors", "path": path.lower(), "colors": umsgpack.Ext(0x17, data.tobytes())}


def _vertices_command(path: Path, positions: np.ndarray) -> dict:
    """The project script's ``set_vertices``: a new ``[N, 3]`` float32 position buffer for the geometry at
    ``path`` (packed as meshcat packs a Float32Array)."""
    data = np.ascontiguousarray(positions, dtype=np.float32)
    return {"type": "set_vertices", "path": path.lower(), "positions": umsgpack.Ext(0x17, data.tobytes())}


class MeshcatViewer:
    """The meshcat page of the demo: the deformed body, the controls, pointer drags and the NeRF view.

    Args:
        host, port: where the page is served (port 0 picks a free one; see :attr:`port` and :attr:`url`).
        nerf_height: height in pixels of the NeRF images rendered for each tab (width from its aspect).
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
        self.nerf_schedules = NerfSchedules(frame_budget)  # checks the budget before the server starts
        self.app = None
        self.nerf_height = int(nerf_height)
        self.background = torch.tensor(background, dtype=torch.float32)
        self._cameras: dict[int, tuple] = {}  # client -> (matrix, fov, aspect) as sent
        self._dragger: int | None = None  # the tab whose press started the drag
        self._lock = threading.Lock()
        self._particle_count = -1
        self._target_shown = False
        self._body = None  # (model, particle count) last shown
        self._tint = None  # [V, 3] the garment's colours last sent
        self.nerf_renders: list[int] = []  # downscale of every NeRF image sent, in order
        self.last_nerf_image: np.ndarray | None = None  # [H, W, 3] uint8, the latest one
        self.message = ""  # the last one shown
        self.server = MeshcatServer(
            host, port, on_message=self.on_message, on_open=self._client_opened, on_close=self._client_closed
        )
        self.port, self.url = self.server.port, self.server.url

    # -- construction ----------------------------------------------------------------------------

    def attach(self, app) -> None:
        """Build the scene and the controls once (tabs that open later receive them from the server)."""
        self.app = app
        sim = app.simulation
        send = self.server.send
        if _is_garment(sim):
            self._attach_garment(app)
            return
        send(SetTransform(Y_UP_TO_Z_UP, Path(_ROOT)).lower(), key="root")
        send(SetProperty("visible", False, Path(("Axes",))).lower(), key="axes")
        geometry = g.TriangularMeshGeometry(
            sim.deformed_mesh_vertices().numpy(), sim.mesh_faces.numpy(), color=sim.mesh_colors.numpy()
        )
        send(SetObject(geometry, g.MeshLambertMaterial(vertexColors=True), _BODY).lower(), key="body")
        self._send_particles(sim)
        self._send_drag_marker(0.25 * sim.particle_radius + 0.01, 0xE03030)
        # The camera in front of the body, the orbit target on the body's centre.
        centre = sim.centre.double().numpy()
        extent = float((sim.mesh_vertices.amax(0) - sim.mesh_vertices.amin(0)).max())
        # meshcat's camera sees 75° vertically: from 1.2 extents away the body fills about half the view's height.
        self._send_camera(centre, centre + extent * np.array([0.0, 0.2, 1.15]))
        self._send_controls()
        self._show(app.render_mode)
        self.report("drag the body with the mouse; click it to pick a point for pin / push / cut")

    def _send_particles(self, sim) -> None:
        positions = sim.particle_positions().numpy()
        colors = sim.particle_colors.numpy().astype(np.float32)
        cloud = g.PointCloud(positions.T, colors.T, size=1.2 * sim.particle_radius)
        self.server.send(SetObject(cloud, path=_PARTICLES).lower(), key="particles")
        self.server.forget(f"vertices {_PARTICLES.lower()}")
        self._particle_count = positions.shape[0]
        if self.app is not None:
            self._show(self.app.render_mode)

    def _send_controls(self) -> None:
        """The controls' ranges and current values, for every tab (again after each change)."""
        sim, app = self.app.simulation, self.app
        if _is_garment(sim):
            self._send_garment_controls()
            return
        material = sim.material
        self.server.send_json(
            {
                "type": "controls",
                "young_modulus": material.young_modulus,
                "poisson_ratio": material.poisson_ratio,
                "density": material.density,
                "damping": sim.config.solver.rayleigh_alpha,
                "gravity": -sim.config.solver.gravity[1],
                "model": material.model,
                "models": list(sim.material_models),
                "kernel_count": sim.model.basis.kernel_count,
                "render_mode": app.render_mode,
                "render_modes": list(RENDER_MODES),
                **self._scene_menu(),
            },
            key="controls",
        )

    def _scene_menu(self) -> dict:
        """The scene menu's part of the controls message: the scene shown and those offered."""
        return {"scene": self.app.scene, "scenes": list(self.app.scenes)}

    def detach(self) -> None:
        """Take the scene off every tab (the root node and everything under it) and stop replaying it to tabs that
        open later; the drag, the tint and the shown body are forgotten."""
        self.server.send(Delete(Path(_ROOT)).lower())
        self.server.forget_all()
        self._particle_count, self._target_shown, self._body, self._tint, self._dragger = -1, False, None, None, None
        self.nerf_schedules.drop()

    def _show(self, mode: str) -> None:
        """Scene nodes of a render mode: the browser's mesh or particles, or the server's NeRF image."""
        send = self.server.send
        send(SetProperty("visible", mode == "mesh", _BODY).lower(), key="body visible")
        send(SetProperty("visible", mode == "particles", _PARTICLES).lower(), key="particles visible")
        send(SetProperty("visible", mode != "nerf", Path(("Grid",))).lower(), key="grid visible")
        send(SetProperty("visible", mode != "nerf", Path(("Background",))).lower(), key="background visible")
        self.server.send_json({"type": "mode", "mode": mode}, key="mode")
        self.nerf_schedules.drop()

    # -- page events (the server's thread: validate, then queue) --------------------------------

    def on_message(self, client: int, message: dict) -> None:
        """Translate one page message into a queued command; raises ValueError for a malformed one.

        A page connects (and sends its camera) as soon as the server listens, which is before the simulation is
        built and attached: its camera is kept, anything else is refused until then. Commands that supersede each
        other are merged while they wait (:class:`pienerf.viewer.loop.CommandQueue`): the latest drag ray, the
        latest value of each control, one reset, one re-sampling."""
        kind = message.get("type")
        if kind not in _TYPES:
            raise ValueError(f"unknown message type {str(kind)[:40]!r}; known: {', '.join(_TYPES)}")
        if kind == "camera":
            view = (message.get("matrix"), message.get("fov"), message.get("aspect"))
            page_cameras(*view, 1)  # validates
            with self._lock:
                self._cameras[client] = (tuple(view[0]), float(view[1]), float(view[2]))
            if self.app is not None:
                self.app.wake()  # a still NeRF view is rendered again from the new camera
            return
        app = self.app
        if app is None:
            raise ValueError(f"{kind} refused: the simulation is still being built; the page shows it when ready")
        if kind == "scene":
            self._checked(app.choose_scene, message.get("name"))
            return
        sim = app.simulation
        if _is_garment(sim) and kind in _GARMENT_ONLY:
            raise ValueError(f"{kind} refused: a garment has no {kind}; drag, pin, release or reset it")
        if kind in ("play", "pause"):
            if _is_garment(sim):
                app.submit(kind, sim.play if kind == "play" else sim.pause, key="play", report=lambda _: self._played())
            else:
                app.submit(kind, lambda: setattr(app, "paused", kind == "pause"), key="play")
            return
        if kind == "pick":
            origin = vector3(message.get("origin"), "ray origin")
            direction = vector3(message.get("direction"), "ray direction")
            self._dragger = client
            app.submit("pick", lambda: sim.pick(origin, direction), report=picked_text)
        elif kind == "drag":
            origin = vector3(message.get("origin"), "ray origin")
            direction = vector3(message.get("direction"), "ray direction")
            # a drag ray after a press that picked nothing moves nothing
            app.submit("drag", lambda: sim.dragging and sim.drag_to(origin, direction), key="drag")
        elif kind == "set":
            self._checked(self._set, message.get("name"), message.get("value"))
        elif kind == "resample":
            count = int(self._checked(control_value, "kernel_count", message.get("kernel_count")))
            resampled = f"resampled with {count} kernels"
            app.submit(
                "resample",
                lambda: sim.resample(count, self._progress("resampling")),
                key="resample",
                heavy=True,
                report=lambda _: resampled,
            )
        elif kind == "release":
            app.submit("release", sim.release)
        elif kind == "pin":
            app.submit("pin", sim.pin_picked, report=lambda _: "pinned the picked region")
        elif kind == "push":
            app.submit("push", sim.push_picked, report=lambda _: "constant force on the picked point")
        elif kind == "cut":
            cut = lambda: sim.cut_picked((0.0, 1.0, 0.0), self._progress("cutting"))  # noqa: E731
            app.submit("cut", cut, heavy=True, report=lambda plane: f"cut through {np.round(plane.point, 3).tolist()}")
        elif _is_garment(sim):
            app.submit("reset", sim.reset, key="reset", report=lambda _: "reset: the rest pose, the garment at rest")
        else:
            app.submit("reset", sim.reset, key="reset", report=lambda _: "reset to rest")

    def _checked(self, translate, *args):
        """``translate(*args)``; a ValueError is shown in the page (the controls go back to the values in use) and
        raised on, so the server drops and counts the message."""
        try:
            return translate(*args)
        except ValueError as error:
            self.report(f"refused: {error}")
            self._send_controls()
            raise

    def _set(self, name, value) -> None:
        app, sim = self.app, self.app.simulation
        if _is_garment(sim):
            self._set_garment(name, value)
            return
        if name == "model":
            if value not in sim.material_models:
                raise ValueError(f"unknown material model {str(value)[:40]!r}; valid: {', '.join(sim.material_models)}")
            app.submit("material model", lambda: self._set_material(model=value), key="set model")
        elif name == "render_mode":
            if value not in RENDER_MODES:
                raise ValueError(f"unknown render mode {str(value)[:40]!r}; valid: {', '.join(RENDER_MODES)}")
            app.submit("render mode", lambda: self.set_render_mode(value), key="set render_mode")
        elif name in _CONTROLS:
            number = control_value(name, value)
            changes = {"gravity": (0.0, -number, 0.0)} if name == "gravity" else {name: number}
            app.submit(name.replace("_", " "), lambda: self._set_material(**changes), key=f"set {name}")
        else:
            raise ValueError(f"unknown control {str(name)[:40]!r}; known: model, render_mode, {', '.join(_CONTROLS)}")

    def _client_opened(self, client: int) -> None:
        if self.app is not None:
            self.app.wake()  # a loop asleep for want of a page runs again

    def has_clients(self) -> bool:
        """Whether a tab is open."""
        return bool(self.server.clients)

    def _client_closed(self, client: int) -> None:
        with self._lock:
            self._cameras.pop(client, None)
        self.nerf_schedules.drop(client)
        if self._dragger == client and self.app is not None:  # a tab closing mid-drag lets go
            self._dragger = None
            self.app.submit("release (tab closed)", self.app.simulation.release)

    # -- commands (the simulation loop's thread) ------------------------------------------------

    def _set_material(self, **changes) -> None:
        material = self.app.simulation.set_material(**changes)
        self._send_controls()
        name, value = next(iter(changes.items()))
        shown = {"young_modulus": lambda v: si_text(v, "Pa"), "gravity": lambda v: f"{-v[1]:.3g} m/s²"}
        self.report(f"{name.replace('_', ' ')} = {shown.get(name, str)(value)} ({material.model})")

    def _progress(self, what: str):
        return lambda stage, fraction: self.show_progress(f"{what}: {stage}", fraction)

    def set_render_mode(self, mode: str) -> None:
        """Switch what the page shows; the first time, the NeRF is fitted in the background (progress in the page)
        and shown once ready, while the simulation goes on."""
        app = self.app
        if mode == "nerf" and "nerf" not in app.simulation.render_backends:
            self._send_controls()  # the menu shows the mode in use until the NeRF is ready
            app.fit_nerf(lambda: self.set_render_mode("nerf"))
            return
        app.render_mode = mode
        self._show(mode)
        self._send_controls()
        self.report(f"showing the {mode}")

    # -- per frame -------------------------------------------------------------------------------

    def update(self, app) -> None:
        """Send this frame: vertex buffers of what is shown, the drag marker, the status; NeRF images."""
        sim, send = app.simulation, self.server.send
        if _is_garment(sim):
            self._update_garment(app)
            return
        body = (id(sim.model), sim.model.basis.kernel_count, sim.particle_positions().shape[0])
        if body != self._body:  # a re-sampling or a cut rebuilt it: new particles, a new kernel count
            self._body = body
            if body[2] != self._particle_count:
                self._send_particles(sim)
            self._send_controls()
        if app.render_mode == "mesh":
            send(
                _vertices_command(_BODY, sim.deformed_mesh_vertices().numpy()),
                key=f"vertices {_BODY.lower()}",
                volatile=True,
            )
        elif app.render_mode == "particles":
            positions = sim.particle_positions().numpy()
            if positions.shape[0] != self._particle_count:
                self._send_particles(sim)
            send(_vertices_command(_PARTICLES, positions), key=f"vertices {_PARTICLES.lower()}", volatile=True)
        elif "nerf" in sim.render_backends:
            self._update_nerf(app)
        self._show_drag_target(sim.drag_target)
        report = sim.last_report
        seconds = sim.time_breakdown()["seconds_per_step"]
        self.server.send_json(
            {
                "type": "status",
                "text": f"{app.fps:.1f} fps, t = {sim.time:.2f} s, {sim.model.basis.kernel_count} kernels, "
                f"{report.iterations} Newton iterations",
                "breakdown": ", ".join(f"{name} {1e3 * value:.1f} ms" for name, value in seconds.items()),
                "fps": app.fps,
            },
            key="status",
            volatile=True,
        )

    def _update_nerf(self, app) -> None:
        """Render the warped NeRF from every tab's camera: as coarse as the frame budget asks while things move,
        refined when still."""
        sim = app.simulation
        with self._lock:
            views = dict(self._cameras)
        for client, view in views.items():
            schedule = self.nerf_schedules.of(client)
            level = schedule.next(sim.state.q, view)
            if level is None:
                continue
            image, _ = nerf_image(app, schedule, page_cameras(*view, self.nerf_height), level, self.background)
            buffer = io.BytesIO()
            Image.fromarray(image).save(buffer, format="JPEG", quality=85)
            data = "data:image/jpeg;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")
            self.server.send_json({"type": "nerf", "image": data, "level": level}, to=client)
            self.nerf_renders.append(level)
            self.last_nerf_image = image

    # -- a garment scene ---------------------------------------------------------------------------------

    def _attach_garment(self, app) -> None:
        """The garment (the pickable body node), the mannequin, the drag marker, the camera and the panel."""
        sim, send = app.simulation, self.server.send
        send(SetTransform(Y_UP_TO_Z_UP, Path(_ROOT)).lower(), key="root")
        send(SetProperty("visible", False, Path(("Axes",))).lower(), key="axes")
        garment = g.TriangularMeshGeometry(
            sim.deformed_mesh_vertices().numpy(), sim.mesh_faces.numpy(), color=sim.vertex_colors().numpy()
        )
        material = g.MeshLambertMaterial(vertexColors=True, side=2)  # both sides: the skirt's inside shows
        send(SetObject(garment, material, _BODY).lower(), key="body")
        self._tint = sim.vertex_colors().numpy()
        body = g.TriangularMeshGeometry(sim.body_vertices().numpy(), sim.body_faces.numpy())
        send(SetObject(body, g.MeshLambertMaterial(color=0xC7BDAD), _AVATAR).lower(), key="avatar")
        self._send_drag_marker(0.012, 0x3050E0)
        centre = sim.centre.double().numpy()
        self._send_camera(centre, centre + np.array([0.0, 0.15, 1.6]))
        send(SetProperty("visible", True, Path(("Grid",))).lower(), key="grid visible")
        send(SetProperty("visible", True, Path(("Background",))).lower(), key="background visible")
        self.server.send_json({"type": "mode", "mode": "mesh"}, key="mode")
        self.nerf_schedules.drop()
        self._send_controls()
        self.report("; ".join(sim.notes) + ". Drag the skirt with the mouse; click it to pick a vertex to pin")

    def _send_garment_controls(self) -> None:
        sim = self.app.simulation
        fabric = sim.fabric
        from_fabric = {"fabric_density": fabric.density, "kappa_s": fabric.kappa_s, "kappa_b": fabric.kappa_b}
        self.server.send_json(
            {
                "type": "controls",
                "kind": "garment",
                **from_fabric,
                "friction": fabric.friction,
                "preset": sim.fabric_name,
                "presets": list(sim.fabric_presets),
                "motion": sim.motion,
                "motions": list(sim.motions),
                "playing": sim.playing,
                "speed": sim.speed,
                "frame": sim.frame,
                "frames": sim.frame_count - 1,
                "render_mode": "mesh",
                "render_modes": ["mesh"],
                **self._scene_menu(),
            },
            key="controls",
        )

    def _played(self) -> str:
        self._send_controls()
        return "playing the motion" if self.app.simulation.playing else "the motion is paused; the garment still moves"

    def _set_garment(self, name, value) -> None:
        app, sim = self.app, self.app.simulation

        def then(verb, text):
            def command():
                result = verb()
                self._send_controls()
                self.report(text(result))

            return command

        if name in GARMENT_CONTROLS:
            keyword, (lo, hi) = GARMENT_CONTROLS[name]
            number = number_in(value, name.replace("_", " "), lo, hi)
            command = then(
                lambda: sim.set_fabric(**{keyword: number}), lambda f: f"{name.replace('_', ' ')} = {number:.3g}"
            )
            app.submit(name, command, key=f"set {name}")
        elif name == "preset":
            if value not in sim.fabric_presets:
                raise ValueError(f"unknown fabric {str(value)[:40]!r}; valid: {', '.join(sim.fabric_presets)}")
            app.submit(
                "preset", then(lambda: sim.apply_preset(value), lambda f: f"fabric: {value} ({f})"), key="set preset"
            )
        elif name == "motion":
            if value not in sim.motions:
                raise ValueError(f"unknown motion {str(value)[:40]!r}; valid: {', '.join(sim.motions)}")
            app.submit("motion", then(lambda: sim.set_motion(value), lambda _: f"motion: {value}"), key="set motion")
        elif name == "speed":
            number = number_in(value, "speed", 0.0, 4.0)
            app.submit("speed", then(lambda: sim.set_speed(number), lambda v: f"speed {v:.2g}x"), key="set speed")
        elif name == "frame":
            number = number_in(value, "frame", 0.0, float(sim.frame_count - 1))
            app.submit("scrub", then(lambda: sim.scrub(number), lambda v: f"to frame {v:.0f}"), key="set frame")
        elif name == "render_mode":
            if value != "mesh":
                raise ValueError(f"a garment scene shows its mesh only, got render mode {str(value)[:40]!r}")
        else:
            known = ", ".join([*GARMENT_CONTROLS, "preset", "motion", "speed", "frame"])
            raise ValueError(f"unknown garment control {str(name)[:40]!r}; known: {known}")

    def _send_drag_marker(self, radius: float, color: int) -> None:
        """The drag marker: a sphere of ``radius`` (m) in ``color`` (0xRRGGBB), hidden until a drag starts."""
        marker = g.Sphere(radius)
        self.server.send(SetObject(marker, g.MeshLambertMaterial(color=color), _TARGET).lower(), key="target")
        self.server.send(SetProperty("visible", False, _TARGET).lower(), key="target visible")

    def _send_camera(self, centre: np.ndarray, position: np.ndarray) -> None:
        """meshcat's /Cameras/default frame at the origin, its camera (in the y-up frame meshcat rotates it into) at
        ``position`` and the orbit target (set by the page's script) at ``centre``, m."""
        send, position = self.server.send, np.asarray(position, dtype=float).tolist()
        send(SetTransform(np.eye(4), Path(("Cameras", "default"))).lower(), key="camera frame")
        camera = Path(("Cameras", "default", "rotated", "<object>"))
        send(SetProperty("position", position, camera).lower(), key="camera")
        self.server.send_json({"type": "view", "target": centre.tolist(), "position": position}, key="view")

    def _show_drag_target(self, target) -> None:
        """The drag marker at ``target`` ``[3]`` (m), shown while there is one and hidden when it goes."""
        send = self.server.send
        if target is not None:
            matrix = np.eye(4)
            matrix[:3, 3] = target.double().cpu().numpy()
            send(SetTransform(matrix, _TARGET).lower(), key="target transform", volatile=True)
        if (target is not None) != self._target_shown:
            self._target_shown = target is not None
            send(SetProperty("visible", self._target_shown, _TARGET).lower(), key="target visible")

    def _update_garment(self, app) -> None:
        """This frame of a garment scene: garment and mannequin vertices, the tint when it changed, the drag
        marker, the status with the contact."""
        sim, send = app.simulation, self.server.send
        send(_vertices_command(_BODY, sim.deformed_mesh_vertices().numpy()), key=f"vertices {_BODY.lower()}",
             volatile=True)  # fmt: skip
        send(_vertices_command(_AVATAR, sim.body_vertices().numpy()), key=f"vertices {_AVATAR.lower()}", volatile=True)
        tint = sim.vertex_colors().numpy()
        if not np.array_equal(tint, self._tint):
            self._tint = tint
            send(_colors_command(_BODY, tint), key=f"colors {_BODY.lower()}")
        self._show_drag_target(sim.drag_target)
        contact = sim.contact()
        report = sim.last_report
        seconds = sim.time_breakdown()["seconds_per_step"]

        def mm(value: float, beyond: float) -> str:
            return f"{1e3 * value:.2f} mm" if math.isfinite(value) else f"> {1e3 * beyond:g} mm"

        contact_text = (
            f"contact: {contact['near']} vertices within d̂ = {1e3 * contact['reach_m']:g} mm (tinted), "
            f"min distance to body {mm(contact['min_body_m'], 100 * contact['reach_m'])}, "
            f"to itself {mm(contact['min_self_m'], contact['reach_m'])}, {contact['inside']} vertices inside the body"
        )
        self.server.send_json(
            {
                "type": "status",
                "text": f"{app.fps:.1f} fps, t = {sim.time:.2f} s, {sim.motion} frame {sim.frame:.0f}"
                f"{'' if sim.playing else ' (paused)'}, {report.newton_iterations} Newton iterations",
                "breakdown": ", ".join(f"{name} {1e3 * value:.1f} ms" for name, value in seconds.items()),
                "contact": contact_text,
                "fps": app.fps,
            },
            key="status",
            volatile=True,
        )

    def show_progress(self, stage: str, fraction: float | None) -> None:
        """The page's progress bar at ``fraction`` with ``stage``, or hidden (``None``)."""
        self.server.send_json({"type": "progress", "stage": stage, "fraction": fraction}, key="progress")

    def report(self, message: str) -> None:
        """Show ``message`` in every tab (and on stderr when none is open)."""
        self.message = message
        self.server.send_json({"type": "message", "text": message}, key="message")
        if not self.server.clients:
            print(message, file=sys.stderr)

    def close(self) -> None:
        self.server.close()
