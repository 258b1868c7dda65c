"""Picking and dragging a garment vertex (no window): the ray's hit, the clamped spring-damper, pins."""

import pytest
import torch

from physavatar.cloth.picking import GarmentDrag
from physavatar.shapes import grid_sheet

F64 = torch.float64


def _drag(**settings) -> tuple[GarmentDrag, torch.Tensor]:
    x, faces = grid_sheet(3, 3, 0.1)  # the xy plane, x and y in 0 .. 0.2 m
    options = {"stiffness": 10.0, "damping": 0.2, "max_force": 0.5, "pin_stiffness": 100.0, **settings}
    return GarmentDrag(faces, **options), x.to(F64)


def test_a_ray_picks_the_hit_triangles_nearest_corner_and_keeps_its_depth(device):
    drag, x = _drag()
    corner = int(((x - torch.tensor([0.1, 0.1, 0.0], dtype=F64)).norm(dim=1)).argmin())
    hit = drag.pick([0.11, 0.09, 1.0], [0.0, 0.0, -1.0], x)
    assert hit is not None and hit.vertex == corner
    assert hit.distance == pytest.approx(1.0, abs=1e-6)
    target = drag.update([0.5, 0.09, 1.0], [0.0, 0.0, -1.0])
    assert torch.allclose(target, torch.tensor([0.5, 0.09, 0.0], dtype=F64), atol=1e-6)  # at the picked depth
    assert drag.pick([0.11, 0.09, 1.0], [0.0, 0.0, 1.0], x) is None and not drag.dragging  # a miss releases


def test_the_spring_is_clamped_in_force_and_damped_as_one_implicit_spring(device):
    """Clamped: ``k ‖t̂ − x‖ = F_max`` for a far target. Damped: ``k (t̂ − x) − c (x − x_n)/h = k' (t' − x)`` for every
    ``x``, with ``k' = k + c/h``."""
    drag, x = _drag()
    drag.grab(4, x)
    drag.update(target=x[4] + torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    dt = 0.04
    index, target, stiffness = drag.springs(x, dt)
    assert index.tolist() == [4]
    clamped = drag.clamped_target(x[4])
    assert float(drag.stiffness * (clamped - x[4]).norm()) == pytest.approx(drag.max_force, rel=1e-12)
    probe = x[4] + torch.tensor([0.01, -0.02, 0.03], dtype=F64)
    force = drag.stiffness * (clamped - probe) - drag.damping * (probe - x[4]) / dt
    assert torch.allclose(force, stiffness[0] * (target[0] - probe), rtol=1e-12, atol=1e-15)
    near = x[4] + torch.tensor([0.01, 0.0, 0.0], dtype=F64)  # 0.1 N: within the clamp, kept
    drag.update(target=near)
    assert torch.equal(drag.clamped_target(x[4]), near)


def test_pins_hold_where_they_were_pinned_and_bad_settings_are_refused(device):
    drag, x = _drag()
    with pytest.raises(RuntimeError, match="click on the garment"):
        drag.pin_picked(x)
    assert drag.springs(x, 0.04) is None
    drag.grab(2, x)
    assert drag.pin_picked(x) == 2 and not drag.dragging
    index, target, stiffness = drag.springs(x + 0.05, 0.04)
    assert index.tolist() == [2] and torch.equal(target[0], x[2]) and stiffness.tolist() == [100.0]
    for name, value in (("stiffness", 0.0), ("damping", -1.0), ("max_force", float("inf"))):
        with pytest.raises(ValueError, match=f"drag {name} must be"):
            _drag(**{name: value})
    with pytest.raises(ValueError, match="not a garment vertex"):
        drag.grab(99, x)
