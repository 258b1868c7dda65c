"""A setting given as 0 is refused with its name, never silently replaced by the default meant for "not given"."""

from __future__ import annotations

import pytest
import torch

from pienerf.nerf.field import NGPConfig, NGPField, OccupancyGrid, render_rays
from pienerf.session import SimulationConfig
from pienerf.sim.model import DiscretizationConfig
from pienerf.sim.picking import DragConfig
from pienerf.sim.solver import SolverConfig


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: SimulationConfig.create("jelly", pin_stiffness=0.0), "pin_stiffness must be a finite positive"),
        (lambda: SimulationConfig.create("jelly", kernel_count=0), "kernel_count must be a positive integer"),
        (lambda: SolverConfig(contact_stiffness=0.0), "contact_stiffness must be > 0 Pa"),
        (lambda: DragConfig(stiffness=0.0), "drag stiffness must be a finite number > 0"),
        (lambda: DiscretizationConfig(kernel_count=4, ip_count=0), "ip_count must be a positive integer"),
    ],
)
def test_a_zero_setting_is_refused_by_name(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_a_zero_ray_chunk_is_refused(device):
    field = NGPField(NGPConfig()).to(device)
    grid = OccupancyGrid(field.aabb.cpu(), 8).to(device)
    rays = torch.zeros(2, 3, device=device), torch.tensor([[0.0, 0.0, 1.0]] * 2, device=device)
    with pytest.raises(ValueError, match="chunk must be a positive number of rays or None"):
        render_rays(field, grid, *rays, chunk=0)
