"""pienerf.session.Simulation: the embedded plant stands under its own weight at the demo's default size, a leaf
follows the drag, and the mesh it hands out belongs to the caller."""

from __future__ import annotations

import torch

from pienerf.session import Simulation, SimulationConfig
from pienerf.viewer import SMOKE


def test_the_default_plant_stands_and_a_leaf_follows_the_drag(device):
    sim = Simulation(SimulationConfig(scene="plant"))  # the demo's own size, material and pins
    rest = sim.mesh_vertices.double()
    height = float(rest[:, 1].max() - rest[:, 1].min())
    sim.step(15)  # 0.5 s
    sag = float((sim.deformed_mesh_vertices().double() - rest).norm(dim=1).max())
    assert sag < 0.03 * height, f"the plant sank {100 * sag / height:.1f} % of its height in 0.5 s under gravity"

    # The leaf particle farthest from the stem, pulled 0.15 m outward.
    particles = sim.model.position.cpu()
    centre = sim.centre.double()
    radial = (particles[:, [0, 2]] - centre[[0, 2]]).norm(dim=1)
    leaf = particles[int(torch.where(particles[:, 1] > 0.3, radial, -1.0).argmax())]
    outward = torch.cat([leaf[:1] - centre[:1], torch.zeros(1, dtype=torch.float64), leaf[2:] - centre[2:]])
    outward = outward / outward.norm()
    sim.grab(leaf)
    start = sim.interaction.drag.position(sim.state.q).cpu()
    sim.drag_to(target=start + 0.15 * outward)
    sim.step(15)  # 0.5 s
    covered = float((sim.interaction.drag.position(sim.state.q).cpu() - start) @ outward) / 0.15
    assert covered > 0.5, f"the leaf covered {covered:.2f} of a 0.15 m drag in 0.5 s"


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
