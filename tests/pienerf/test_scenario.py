"""pienerf.scenario and SimulationConfig.create: flat settings reach the right part, keyframes interpolate, colliders
follow their keys, and bad input names the key."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from pienerf.scenario import (
    ScenarioError,
    keyframe,
    load_scenario,
    scenario_cameras,
    scenario_colliders,
    volume_sample_frames,
)
from pienerf.session import INTERACTIVE_DISCRETIZATION, INTERACTIVE_SOLVER, SCENE_SETUPS, SimulationConfig
from pienerf.sim.picking import DragConfig


def test_create_sends_each_flat_setting_to_its_part():
    config = SimulationConfig.create(
        "jelly", kernel_count=6, lloyd_iterations=0, rayleigh_alpha=1.5, drag_max_acceleration=12.0, seed=3
    )
    assert config.seed == 3 and config.solver.rayleigh_alpha == 1.5
    assert config.solver.newton_iterations == INTERACTIVE_SOLVER.newton_iterations
    assert config.discretization.kernel_count == 6
    assert config.discretization.kernel_lloyd_iterations == config.discretization.ip_lloyd_iterations == 0
    assert config.drag == DragConfig(max_acceleration=12.0)
    default = SimulationConfig.create("jelly", kernel_count=None)
    assert default.discretization is None
    assert default.body_discretization() == replace(
        INTERACTIVE_DISCRETIZATION, kernel_count=SCENE_SETUPS["jelly"].kernel_count
    )
    with pytest.raises(ValueError, match="unknown simulation setting 'youngs_modulus'"):
        SimulationConfig.create("jelly", youngs_modulus=1e4)
    with pytest.raises(ValueError, match="drag stiffness"):
        DragConfig(stiffness=-1.0)


def test_keyframes_interpolate_and_hold_past_the_ends():
    keys = [[0.0, [0.0, 0.0, 0.0]], [1.0, [1.0, 2.0, 0.0]]]
    torch.testing.assert_close(keyframe(keys, 0.25, "k"), torch.tensor([0.25, 0.5, 0.0], dtype=torch.float64))
    torch.testing.assert_close(keyframe(keys, 5.0, "k"), torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64))
    with pytest.raises(ScenarioError, match="'drags\\[0\\].keys' must be"):
        keyframe([[1.0, [0.0, 0.0, 0.0]], [0.0, [1.0, 0.0, 0.0]]], 0.5, "drags[0].keys")


def test_colliders_and_cameras_follow_the_scenario():
    scenario = {
        "colliders": [{"type": "plane", "normal": [0.0, -1.0, 0.0], "keys": [[0.0, [0, 1, 0]], [1.0, [0, 0.5, 0]]]}],
        "cameras": {"type": "orbit", "azimuths": [0.0, 90.0], "width": 8, "height": 6},
    }
    floor, plane = scenario_colliders(scenario, 0.5, floor=True)
    assert plane.point == pytest.approx((0.0, 0.75, 0.0))
    assert len(scenario_colliders(scenario, 0.5, floor=False)) == 1
    cameras = scenario_cameras(scenario, [0.0, 0.2, 0.0], 0.0)
    assert len(cameras) == 2 and (cameras.width, cameras.height) == (8, 6)
    with pytest.raises(ScenarioError, match="'colliders\\[0\\].type'"):
        scenario_colliders({"colliders": [{"type": "cone"}]}, 0.0, floor=False)


SCENARIOS = Path(__file__).resolve().parents[2] / "assets" / "scenarios"


def test_volume_samples_take_the_nearest_frame_and_refuse_times_past_the_run():
    samples = [{"time": t, "label": f"{t} s"} for t in (2.0, 0.5, 1.0)]
    scenario = {"solver": {"dt": 0.0333333, "frames": 60}, "volume_samples": samples}
    frames = volume_sample_frames(scenario)
    assert [s["frame"] for s in frames] == [15, 30, 60]  # 60 × 0.0333333 s < 2.0 s still samples t = 2 s
    assert [s["label"] for s in frames] == ["0.5 s", "1.0 s", "2.0 s"]
    scenario["volume_samples"].append({"time": 2.5})
    with pytest.raises(ScenarioError, match=r"volume_samples\[3\].time' = 2.5 s lies outside the run"):
        volume_sample_frames(scenario)


def test_smoke_size_keeps_every_volume_sample_inside_its_short_run():
    full = load_scenario(SCENARIOS / "jelly_compression.toml")
    smoke = load_scenario(SCENARIOS / "jelly_compression.toml", smoke=True)
    assert [s["frame"] for s in volume_sample_frames(full)] == [15, 30, 60]
    frames = volume_sample_frames(smoke)
    assert len(frames) == 3 and all(s["frame"] == smoke["solver"]["frames"] for s in frames)
    assert all("smoke" in s["label"] for s in frames)


def test_cameras_up_turns_the_view_with_the_world():
    scenario = {"cameras": {"type": "orbit", "azimuths": [0.0], "elevation": 30.0, "width": 8, "height": 6}}
    y_up = scenario_cameras(scenario, [0.0, 0.0, 0.0], 0.0)
    scenario["cameras"]["up"] = [0.0, 0.0, 1.0]
    z_up = scenario_cameras(scenario, [0.0, 0.5, 0.0], 0.0)
    assert y_up.c2w[0, 1, 1] > 0.8  # the image's up is +y ...
    assert z_up.c2w[0, 2, 1] > 0.8 and z_up.c2w[0, 2, 3] > 0.5  # ... and +z, the camera above the centre along z
    forward = -z_up.c2w[0, :3, 2]
    to_centre = torch.tensor([0.0, 0.5, 0.0]) - z_up.c2w[0, :3, 3]
    assert torch.nn.functional.cosine_similarity(forward, to_centre, dim=0) > 0.999  # still looking at the centre
    scenario["cameras"]["up"] = [0.0, 0.0, 0.0]
    with pytest.raises(ScenarioError, match="'cameras.up' must be a non-zero direction"):
        scenario_cameras(scenario, [0.0, 0.0, 0.0], 0.0)
