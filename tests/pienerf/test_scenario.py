"""pienerf.scenario and SimulationConfig.create: flat settings reach the right part, keyframes interpolate, colliders
follow their keys, and bad input names the key."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from pienerf.picking import DragConfig
from pienerf.scenario import ScenarioError, keyframe, scenario_cameras, scenario_colliders
from pienerf.session import INTERACTIVE_DISCRETIZATION, INTERACTIVE_SOLVER, SCENE_SETUPS, SimulationConfig


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
