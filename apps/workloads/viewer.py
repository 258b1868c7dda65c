"""The interactive viewer's per-frame work on the plant: one simulation step plus one render from a browser camera.

``viewer_frame``: ``Simulation.step()`` + ``Simulation.render(mode="mesh")`` at 320×240 (smoke: 160×120, large:
640×480), what
:mod:`apps.demo` does each frame in its default mode. ``viewer_frame_nerf``: the same with the warped-NeRF mode
(quadratic ray warping of the plant's NeRF, fitted on first use and cached, see
:func:`pienerf.scenes.scene_nerf`) at full resolution, what the viewer shows once the camera is still.
Throughput is frames per second of step + render; the record also gives the median step and the median render
(``step_median_s``, ``render_median_s``) of the timed frames, since the two scale differently with the size.

``viewer_frame_avatar``: the frame of ``apps.demo --scene avatar`` while the user drags: one garment step of
:class:`physavatar.session.AvatarSimulation` (the mannequin walking, the front of the hem dragged by a target that
sways sideways by ±12 cm over 2 s, as a hand on the mouse) and one mesh update as the meshcat viewer makes it (the
garment's and the mannequin's vertex buffers packed as the page's ``set_vertices``, the tint, the contact counters).
The garment is the session's choice for the device at ``paper`` size (the procedural skirt of 96 vertices on the
CPU, skirt7271 on CUDA), the 60-vertex procedural skirt at ``smoke`` size and skirt7271 at ``large`` size. The
record carries the median step and update (``step_median_s``, ``update_median_s``), the session's time breakdown
(``breakdown_s``: each part's median over the frames run, so that the first frames' kernel builds do not count),
the Newton iterations and the most vertices found inside the body over the timed frames (``vertices_inside_body``,
0 by the barrier's guarantee).

``avatar_inside``: that frame's test for garment vertices inside the body (the counter on the page), on the same
garment and body: the generalised winding number as the exact sum of every body face's solid angle
(``MeshBVH.inside(method="direct")``), beside the BVH's fast winding number (``method="tree"``) as the reference.
The record says whether the two found the same vertices inside (``agree``) and how many (``inside``).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time

import numpy as np
import torch
import umsgpack

from apps.workloads import Case, WorkloadUnavailable, workload
from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.garment import SHARED_GARMENTS
from physavatar.session import AvatarConfig, AvatarSimulation
from pienerf.nerf.cameras import orbit_cameras
from pienerf.nerf.fitting import NerfFit
from pienerf.scenes import scene_nerf
from pienerf.session import Simulation, SimulationConfig

_SIZE = {"smoke": (160, 120), "paper": (320, 240), "large": (640, 480)}


def _case(size: str, mode: str) -> Case:
    simulation = Simulation(SimulationConfig(scene="plant"))
    if mode == "nerf":
        fit = NerfFit()  # the viewer's own fit, so its cached checkpoint is reused
        if size == "smoke":
            fit = dataclasses.replace(fit, views=12, resolution=32, train=dataclasses.replace(fit.train, steps=50))
        trained = scene_nerf("plant", fit)
        simulation.add_nerf_render(trained.field, trained.grid)
    width, height = _SIZE[size]
    centre = simulation.mesh_vertices.float().mean(0).tolist()
    cameras = orbit_cameras(centre, 1.6, [30.0], 20.0, width, height)

    step_times, render_times, extra = [], [], {}

    def run():
        clock = time.perf_counter()
        simulation.step()
        backend.synchronize()
        middle = time.perf_counter()
        frame = simulation.render(cameras, 0, mode)
        backend.synchronize()
        step_times.append(middle - clock)
        render_times.append(time.perf_counter() - middle)
        extra.update(step_median_s=statistics.median(step_times), render_median_s=statistics.median(render_times))
        return frame.rgba

    return Case(
        run=run,
        reference=None,
        params={"scene": "plant", "mode": mode, "size": f"{width}x{height}"},
        work=1.0,
        unit="frames/s",
        extra=extra,
    )


@workload("viewer_frame", "the viewer's frame on the plant: one step + one mesh render from a browser camera")
def bench_viewer_frame(device: str, size: str) -> Case:
    return _case(size, "mesh")


@workload("viewer_frame_nerf", "the viewer's frame on the plant: one step + one warped-NeRF render")
def bench_viewer_frame_nerf(device: str, size: str) -> Case:
    return _case(size, "nerf")


_AVATAR_GARMENT = {"smoke": "procedural", "paper": None, "large": "skirt7271"}
_SWAY = 0.12  # m, the drag target's sideways swing
_SWAY_PERIOD = 2.0  # s


def _packed(positions: torch.Tensor) -> bytes:
    """A vertex buffer as the meshcat viewer sends it: float32 bytes in a msgpack extension."""
    data = np.ascontiguousarray(positions.numpy(), dtype=np.float32)
    return umsgpack.packb({"type": "set_vertices", "positions": umsgpack.Ext(0x17, data.tobytes())})


def _avatar_session(name: str, size: str) -> AvatarSimulation:
    """The avatar viewer's session with the garment of ``size`` (module docstring), for the workload ``name``."""
    if size == "large" and not (SHARED_GARMENTS / "skirt7271.obj").is_file():
        raise WorkloadUnavailable(
            f"{name} --size large needs the DiffCloth skirt skirt7271.obj, absent from {SHARED_GARMENTS}; "
            "put the project's shared data folder beside the checkout"
        )
    skirt = (5, 12) if size == "smoke" else AvatarConfig().skirt
    return AvatarSimulation(AvatarConfig(garment=_AVATAR_GARMENT[size], skirt=skirt))


@workload("viewer_frame_avatar", "the avatar viewer's frame while dragging: one garment step + one mesh update")
def bench_viewer_frame_avatar(device: str, size: str) -> Case:
    simulation = _avatar_session("viewer_frame_avatar", size)
    x = simulation.state.x.cpu()
    front = x[:, 2] > x[:, 2].mean()
    hem = int(torch.where(front, x[:, 1], torch.full_like(x[:, 1], math.inf)).argmin())
    simulation.grab(hem)
    start = x[hem].double()
    step_times, update_times = [], []
    parts: dict[str, list[float]] = {}  # each frame's seconds by the session's phases
    extra: dict = {"notes": list(simulation.notes), "vertices_inside_body": 0}

    def phase_totals() -> dict[str, float]:
        breakdown = simulation.time_breakdown()
        return {name: value * breakdown["steps"] for name, value in breakdown["seconds_per_step"].items()}

    def run():
        before = phase_totals()
        clock = time.perf_counter()
        sway = _SWAY * math.sin(2.0 * math.pi * simulation.time / _SWAY_PERIOD)
        simulation.drag_to(target=start + torch.tensor([sway, 0.0, 0.0], dtype=torch.float64))
        report = simulation.step()
        backend.synchronize()
        middle = time.perf_counter()
        sent = len(_packed(simulation.deformed_mesh_vertices())) + len(_packed(simulation.body_vertices()))
        colors = simulation.vertex_colors()
        contact = simulation.contact()
        update_times.append(time.perf_counter() - middle)
        step_times.append(middle - clock)
        for name, total in phase_totals().items():
            parts.setdefault(name, []).append(total - before.get(name, 0.0))
        extra.update(
            step_median_s=statistics.median(step_times),
            update_median_s=statistics.median(update_times),
            newton_iterations=report.newton_iterations,
            bytes_sent=sent + colors.numel() * 4,
            vertices_inside_body=max(extra["vertices_inside_body"], contact["inside"]),
            min_distance_body=contact["min_body_m"] if math.isfinite(contact["min_body_m"]) else None,
            breakdown_s={name: statistics.median(seconds) for name, seconds in parts.items()},
        )
        return simulation.state.x

    summary = simulation.summary()
    return Case(
        run=run,
        reference=None,
        params={
            "scene": "avatar",
            "garment": summary["garment"],
            "garment_vertices": summary["garment_vertices"],
            "body_vertices": summary["body_vertices"],
            "motion": summary["motion"],
            "dragging": True,
        },
        work=1.0,
        unit="frames/s",
        extra=extra,
        frame_seconds=simulation.dt,
    )


@workload("avatar_inside", "the avatar viewer's inside test: solid-angle sum over the body's faces vs the BVH's")
def bench_avatar_inside(device: str, size: str) -> Case:
    simulation = _avatar_session("avatar_inside", size)
    simulation.step()  # the garment settled one frame onto the walking body
    body = simulation.body_now.to(torch.float32)
    bvh = MeshBVH(body, simulation.body_faces.to(body.device), winding_numbers=True)
    x = simulation.state.x.to(torch.float32)
    direct = bvh.inside(x, method="direct")  # the same points every repetition: compared once
    extra = {"agree": bool(torch.equal(direct, bvh.inside(x, method="tree"))), "inside": int(direct.sum())}

    return Case(
        run=lambda: bvh.inside(x, method="direct"),
        reference=lambda: bvh.inside(x, method="tree"),
        reference_name="fast winding number through the BVH (Warp)",
        params={
            "garment_vertices": int(x.shape[0]),
            "body_faces": int(simulation.body_faces.shape[0]),
        },
        work=x.shape[0] / 1e6,
        unit="Mpoints/s",
        extra=extra,
    )
