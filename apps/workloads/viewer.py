"""The interactive viewer's per-frame work on the plant: one simulation step plus one render from a browser camera.

``viewer_frame``: ``Simulation.step()`` + ``Simulation.render(mode="mesh")`` at 320×240 (smoke: 160×120, large:
640×480), what
:mod:`apps.demo` does each frame in its default mode. ``viewer_frame_nerf``: the same with the warped-NeRF mode
(quadratic ray warping of the plant's NeRF, fitted on first use and cached, see
:func:`pienerf.scenes.scene_nerf`) at full resolution, what the viewer shows once the camera is still.
Throughput is frames per second of step + render; the record also gives the median step and the median render
(``step_median_s``, ``render_median_s``) of the timed frames, since the two scale differently with the size.
"""

from __future__ import annotations

import dataclasses
import statistics
import time

from apps.workloads import Case, workload
from kernels import backend
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
