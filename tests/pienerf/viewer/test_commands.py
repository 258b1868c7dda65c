"""The demo loop's command queue stays bounded and merges what supersedes, the loop sleeps while nobody watches or
the body rests and wakes at the next command, and a page that connects before the simulation is built is served."""

from __future__ import annotations

import threading
from dataclasses import replace

import pytest
import torch

from kernels import backend
from pienerf.nerf.fitting import NerfFit
from pienerf.nerf.training import load_checkpoint
from pienerf.viewer import build_app, loop
from pienerf.viewer.loop import MAX_PENDING_COMMANDS, REST_FRAMES, CommandQueue
from pienerf.viewer.meshcat_viewer import MeshcatViewer
from pienerf.viewer.nerf_job import FIRST_FIT, shipped_nerf, shipped_nerf_path

CLIENT = 1
_Z = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)  # a drag ray starts this far in front of its point


@pytest.fixture(scope="module")
def app(request):
    backend.init(request.config.getoption("--device") or backend.default_device())
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True)
    yield app
    app.viewer.close()


def test_the_queue_merges_superseded_commands_and_refuses_past_its_limit():
    ran: list[str] = []
    commands = CommandQueue(limit=4)
    for i in range(10_000):
        commands.put("reset", lambda: ran.append("reset"), key="reset")
        commands.put("drag", lambda i=i: ran.append(f"drag {i}"), key="drag")
    commands.put("pin", lambda: ran.append("pin"))
    commands.put("reset", lambda: ran.append("reset"), key="reset")  # moves behind the pin
    assert len(commands) == 3
    commands.put("cut", lambda: ran.append("cut"), heavy=True)
    with pytest.raises(ValueError, match="4 commands are already waiting"):
        commands.put("cut", lambda: ran.append("cut"), heavy=True)
    for _what, command in commands.take():
        command()
    assert ran == ["drag 9999", "pin", "reset", "cut"]
    commands.put("cut", lambda: ran.append("cut 1"), heavy=True)
    commands.put("pin", lambda: ran.append("pin 1"))
    commands.put("cut", lambda: ran.append("cut 2"), heavy=True)
    assert [what for what, _ in commands.take()] == ["cut", "pin"]  # one rebuild a frame
    assert [what for what, _ in commands.take()] == ["cut"]
    assert commands.empty()


def test_a_flood_of_page_messages_stays_bounded_and_the_loop_keeps_stepping(app):
    viewer = app.viewer
    for _ in range(5_000):
        viewer.on_message(CLIENT, {"type": "reset"})
    assert len(app.commands) == 1
    for _ in range(3):
        viewer.on_message(CLIENT, {"type": "resample", "kernel_count": 6})  # merged into one
    assert len(app.commands) == 2
    refused = 0
    for _ in range(2 * MAX_PENDING_COMMANDS):
        try:
            viewer.on_message(CLIENT, {"type": "push"})  # distinct commands: queued up to the limit
        except ValueError:
            refused += 1
    assert len(app.commands) == MAX_PENDING_COMMANDS and refused == MAX_PENDING_COMMANDS + 2
    time = app.simulation.time
    app.tick()
    assert app.simulation.time > time  # the frame stepped after running what waited
    assert app.commands.empty()
    app.errors.clear()


def test_the_loop_rests_without_a_page_or_when_still_and_wakes_on_a_command(app, monkeypatch):
    assert not app.viewer.has_clients() and app.resting  # no tab: nothing to show
    monkeypatch.setattr(app.viewer, "has_clients", lambda: True)
    app.still_frames = 0
    assert not app.resting
    app.paused = True  # a paused body is still
    try:
        for _ in range(REST_FRAMES):
            app.tick()
        assert app.resting
        app.submit("reset", app.simulation.reset, key="reset")
        assert not app.resting and app.still_frames == 0
        app.tick()
        app.simulation.grab(app.simulation.model.position[0])  # a drag in progress keeps it awake
        for _ in range(REST_FRAMES):
            app.tick()
        assert not app.resting
        app.simulation.release()
    finally:
        app.paused = False


def test_a_sleeping_loop_runs_the_next_command():
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True)
    ran = threading.Event()
    loop = threading.Thread(target=app.run, daemon=True)
    try:
        assert app.resting  # no tab is open: run() sleeps
        loop.start()
        app.submit("probe", ran.set)
        assert ran.wait(60.0), "the loop did not wake for a command"
    finally:
        app.close()
        loop.join(60.0)
    assert not loop.is_alive()


def test_a_page_connecting_before_the_simulation_is_built_is_not_an_error():
    viewer = MeshcatViewer("127.0.0.1", 0)  # build_app starts the page's server first, then builds
    try:
        camera = {"type": "camera", "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 3, 1], "fov": 50, "aspect": 1}
        viewer.on_message(CLIENT, camera)  # the page's first message, sent on connect
        with pytest.raises(ValueError, match="still being built"):
            viewer.on_message(CLIENT, {"type": "reset"})
        assert not viewer.has_clients()
    finally:
        viewer.close()


class _TwoFits:
    """Stands in for NerfJob: reports its first fit ready, then its second, as the fitting process does."""

    def __init__(self, scene, fit, cache_dir):
        self.fits = [fit, replace(fit, seed=1)]
        self.ready, self.finished, self.error, self.polls = 0, False, None, 0

    def poll(self):
        self.polls += 1
        self.ready = min(self.polls, 2)
        self.finished = self.polls >= 2
        return [("training", 0.5)]

    def cancel(self):
        self.finished = True


def test_the_first_nerf_shows_and_the_refined_one_takes_its_place(tmp_path, monkeypatch):
    monkeypatch.setattr(loop, "NerfJob", _TwoFits)
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True, cache_dir=str(tmp_path))
    try:
        app.viewer.on_message(CLIENT, {"type": "set", "name": "render_mode", "value": "nerf"})
        app.tick()  # starts the job, whose first poll has the first fit ready
        assert app.render_mode == "nerf" and app.nerf_job is not None
        first = app.simulation.render_backends["nerf"]
        app.tick()
        assert app.nerf_job is None and app.render_mode == "nerf"
        assert app.simulation.render_backends["nerf"] is not first, "the refined NeRF did not replace the first"
        assert app.errors == []
    finally:
        app.close()


def _plant_nerf_app(fit):
    """The smoke plant behind a meshcat viewer whose one tab (no socket) looks at it, asking for ``fit``'s NeRF."""
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True)
    app.nerf_options["fit"] = fit
    centre = app.simulation.centre.double().tolist()
    matrix = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, centre[0], centre[1] + 0.2, centre[2] + 1.5, 1]
    app.viewer.on_message(CLIENT, {"type": "camera", "matrix": matrix, "fov": 60, "aspect": 1.5})
    return app


def test_the_shipped_nerf_shows_at_once_and_the_loop_keeps_stepping_and_serving(monkeypatch):
    """Choosing the NeRF view loads the shipped NeRF in the same frame; then, while a drag keeps the plant moving,
    every frame steps and renders one image (coarse), and once still the loop renders the refined image once and
    then nothing: it neither stops stepping nor re-renders forever."""
    monkeypatch.setattr(loop, "NerfJob", None)  # no fitting process may start
    app = _plant_nerf_app(FIRST_FIT)
    try:
        sim, viewer = app.simulation, app.viewer
        viewer.on_message(CLIENT, {"type": "set", "name": "render_mode", "value": "nerf"})
        app.tick()
        assert app.render_mode == "nerf" and app.nerf_job is None and app.errors == []
        assert len(viewer.nerf_renders) == 1 and viewer.last_nerf_image is not None
        top = sim.model.position[int(sim.model.position[:, 1].argmax())].double().cpu()
        sim.grab(top)
        for frame in range(8):
            side = torch.tensor([0.08 if frame % 2 else -0.08, 0.0, 0.0], dtype=torch.float64)
            viewer.on_message(CLIENT, {"type": "drag", "origin": (top + side + _Z).tolist(), "direction": [0, 0, -1]})
            before, renders = sim.time, len(viewer.nerf_renders)
            app.tick()
            assert sim.time > before, f"frame {frame} did not step"
            assert len(viewer.nerf_renders) == renders + 1, f"frame {frame} served no NeRF image"
        assert max(viewer.nerf_renders[1:]) > 1  # coarse while moving
        app.paused = True  # the body stands still: one refined image, then none
        renders = len(viewer.nerf_renders)
        for _ in range(4):
            app.tick()
        assert viewer.nerf_renders[renders:] == [1] and app.errors == []
    finally:
        app.close()


def test_the_default_fit_refines_the_shipped_nerf_in_the_background(monkeypatch):
    monkeypatch.setattr(loop, "NerfJob", _TwoFits)
    app = _plant_nerf_app(None)
    try:
        app.viewer.on_message(CLIENT, {"type": "set", "name": "render_mode", "value": "nerf"})
        app.tick()  # the shipped NeRF at once; the job (default fit) starts
        shipped = app.simulation.render_backends["nerf"]
        assert app.render_mode == "nerf" and isinstance(app.nerf_job, _TwoFits)
        assert app.nerf_job.fits[0] == NerfFit()
        for _ in range(3):
            app.tick()
        assert app.nerf_job is None and app.render_mode == "nerf" and app.errors == []
        assert app.simulation.render_backends["nerf"] is not shipped, "the default fit did not replace the shipped NeRF"
    finally:
        app.close()


def test_the_shipped_nerf_is_compact_loads_and_matches_the_first_fit(device):
    """The plant's shipped NeRF is named by the viewer's first fit (a changed fit or recipe must regenerate it:
    ``python -m apps.demo --build-nerf-asset``), stores float16 weights in under 2 MB, and the checkpoint loader
    reads it as float32 with the first fit's architecture."""
    path = shipped_nerf_path("plant")
    assert path.is_file(), "the plant's NeRF asset is missing or stale: run python -m apps.demo --build-nerf-asset"
    assert path.stat().st_size < 2 * 2**20
    stored = torch.load(path, map_location="cpu", weights_only=True)
    assert stored["field"]["encoding.table"].dtype == torch.float16 and stored["optimizer"] is None
    trained = load_checkpoint(path)
    assert trained.field.config == FIRST_FIT.ngp
    assert all(p.dtype == torch.float32 for p in trained.field.parameters())
    assert shipped_nerf("plant") and shipped_nerf("plant", FIRST_FIT) and not shipped_nerf("plant", NerfFit())
    assert not shipped_nerf("teapot")
