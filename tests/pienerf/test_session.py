"""pienerf.session.Simulation: the mesh it hands out belongs to the caller."""

from __future__ import annotations

import torch

from pienerf.session import Simulation, SimulationConfig
from pienerf.viewer import SMOKE


def test_deformed_mesh_vertices_are_a_copy_the_next_step_leaves_alone(device):
    sim = Simulation(SimulationConfig.create("plant", **SMOKE))
    first = sim.deformed_mesh_vertices()
    kept = first.clone()
    sim.step(3)
    second = sim.deformed_mesh_vertices()
    assert not torch.equal(second, kept), "three steps under gravity left the mesh where it was"
    assert torch.equal(first, kept), "the next call overwrote the vertices handed out before"
    second += 1.0  # the caller may write to its copy
    torch.testing.assert_close(sim.deformed_mesh_vertices(), second - 1.0)
