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


def test_a_leaf_dragged_hard_leaves_the_pot_still(device):
    sim = Simulation(SimulationConfig(scene="plant"))  # the demo's own size, material and pins
    particles = sim.model.position.cpu()
    centre = sim.centre.double()
    radial = (particles[:, [0, 2]] - centre[[0, 2]]).norm(dim=1)
    leaf = particles[int(torch.where(particles[:, 1] > 0.3, radial, -1.0).argmax())]
    outward = torch.cat([leaf[:1] - centre[:1], torch.zeros(1, dtype=torch.float64), leaf[2:] - centre[2:]])
    sim.grab(leaf)
    start = sim.interaction.drag.position(sim.state.q).cpu()
    sim.drag_to(target=start + outward / outward.norm())  # 1 m out: the spring pulls at its clamp
    pot = particles[:, 1] < 0.29  # the pot's rim (pienerf.scenes: the pot is lathed up to y = 0.29 m)
    rest = sim.particle_positions().double()[pot]
    # The pins are springs of k_pin per particle. However the pot shares the load, no pin stretches farther than if
    # it alone held the whole pull, which is at most the drag's clamped force a_max · m_eff (m_eff = 1 / w, the
    # picked point's effective mass), plus the body's weight: δ ≤ (a_max / w + m g) / k_pin (18 mm here; with only
    # the pot's floor pinned the pot swung 68 mm).
    drag = sim.interaction.drag
    weight = sim.material.density * float(sim.model.volume.sum()) * 9.81
    bound = (sim.config.drag.max_acceleration / float(drag.inverse_mass[0]) + weight) / sim.interaction.pin_stiffness
    moved = 0.0
    for _ in range(30):  # 1 s
        sim.step()
        moved = max(moved, float((sim.particle_positions().double()[pot] - rest).norm(dim=1).max()))
    assert float((drag.position(sim.state.q).cpu() - start).norm()) > 0.2, "the leaf did not follow the drag"
    assert moved < bound, f"the pot moved {1e3 * moved:.1f} mm, more than {1e3 * bound:.1f} mm"
