"""The refinement schedule holds a frame budget while things move and refines once when still."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from pienerf.render.previews import NerfRenderBackend, ViewRays
from pienerf.render.refinement import RefinementSchedule
from pienerf.scenes import MeshAlbedoField, scene_cameras, scene_density
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.sampling import grid_sample


def test_refinement_schedule_is_coarse_while_moving_and_refines_once_when_still():
    schedule = RefinementSchedule(moving=4, still=1, tolerance=1e-4)
    q = torch.zeros(5, 3, dtype=torch.float64)
    assert schedule.next(q, "view a") == 4
    assert schedule.next(q + 1e-5, "view a") == 1, "still: refine"
    assert schedule.next(q, "view a") is None, "already refined"
    assert schedule.next(q + 1e-3, "view a") == 4, "the body moved"
    assert schedule.next(q + 1e-3, "view b") == 4, "the camera moved"
    assert [schedule.next(q + 1e-3, "view b") for _ in range(3)] == [1, None, None]


def _drag(schedule: RefinementSchedule, render_seconds, step_seconds: float, frames: int) -> list[int]:
    """Levels of ``frames`` moving frames, each render reported as taking ``render_seconds(level)``."""
    q, levels = torch.zeros(5, 3, dtype=torch.float64), []
    for frame in range(frames):
        level = schedule.next(q + 1e-2 * (frame + 1), "view")
        levels.append(level)
        schedule.record(level, render_seconds(level), step_seconds)
    return levels


def _pixels(cost_per_pixel: float, width: int = 320, height: int = 240):
    """A renderer whose time is proportional to the pixels it renders at a downscale."""
    return lambda level: cost_per_pixel * math.ceil(width / level) * math.ceil(height / level)


def test_a_slow_render_drives_the_level_coarser_until_the_frame_budget_holds():
    budget, step = 1 / 30, 0.008
    render = _pixels(2e-6)  # 0.15 s at full resolution: level 3 fits (0.017 + 0.008 s), level 2 does not
    levels = _drag(RefinementSchedule(frame_budget=budget), render, step, 12)
    assert levels[:2] == [4, 4], "the start level until a render is measured (the first is not)"
    assert set(levels[2:]) == {3}, levels
    assert step + render(3) <= budget < step + render(2), "the finest level that fits"

    schedule = RefinementSchedule(frame_budget=budget)
    slower = _drag(schedule, _pixels(4e-5), step, 12)
    assert set(slower[2:]) == {8} and schedule.predicted_seconds(8) > budget, f"nothing fits: the coarsest {slower}"


def test_a_render_bound_by_its_fixed_cost_keeps_its_sharpness():
    """When a render costs about the same at every size (set-up, encoding), no coarser level would buy frames:
    the schedule keeps the finest level within ``overrun`` of the coarsest one's time instead of the coarsest."""
    budget, step = 1 / 30, 0.008
    pixels = _pixels(1e-8)  # 0.8 ms of pixels at full resolution, on top of a fixed 45 ms
    schedule = RefinementSchedule(frame_budget=budget)
    levels = _drag(schedule, lambda level: 0.045 + pixels(level), step, 12)
    assert schedule.predicted_seconds(8) > budget, "nothing fits"
    assert set(levels[3:]) == {1}, levels
    assert schedule.fixed_cost == pytest.approx(0.045, rel=1e-3)

    # a fixed cost beside a large per-pixel one: the coarser levels still pay, up to where they stop paying
    mixed = RefinementSchedule(frame_budget=budget)
    levels = _drag(mixed, lambda level: 0.045 + _pixels(5e-7)(level), step, 12)
    finest = levels[-1]
    assert 1 < finest < 8 and set(levels[4:]) == {finest}, levels
    assert mixed.predicted_seconds(finest) <= 1.15 * mixed.predicted_seconds(8) < mixed.predicted_seconds(finest - 1)


def test_a_fast_render_drives_the_level_down_to_full_resolution():
    levels = _drag(RefinementSchedule(moving=4, still=1, frame_budget=1 / 30), _pixels(1e-7), 0.005, 8)
    assert levels[:2] == [4, 4] and set(levels[2:]) == {1}, levels


def test_still_refines_once_at_full_resolution_then_renders_nothing():
    schedule = RefinementSchedule(frame_budget=1 / 30)
    levels = _drag(schedule, _pixels(2e-6), 0.008, 6)
    assert levels[-1] == 3
    q = torch.zeros(5, 3, dtype=torch.float64) + 6e-2
    assert [schedule.next(q, "view") for _ in range(3)] == [1, None, None]
    assert schedule.next(q + 1e-2, "view") == 3, "moving again: the learned level, not the start one"


def test_a_prediction_hovering_at_the_budget_keeps_the_level():
    budget, step = 1 / 30, 0.005
    at_3 = _pixels(1.0)(3)
    schedule, q = RefinementSchedule(moving=3, frame_budget=budget), torch.zeros(5, 3, dtype=torch.float64)
    levels, missed = [], False
    for frame, factor in enumerate(([0.88] * 5 + [1.12] * 5) * 3):
        level = schedule.next(q + 1e-2 * (frame + 1), "view")
        levels.append(level)
        # a render that fills the frame budget at level 3, give or take 12 %
        schedule.record(level, factor * (budget - step) * _pixels(1.0)(level) / at_3, step)
        missed |= (schedule.predicted_seconds(3) or 0.0) > budget
    assert missed, "the prediction at level 3 went over the budget at times"
    assert set(levels) == {3}, f"the level flip-flops: {levels}"


def test_bad_budgets_and_levels_are_refused_with_the_fix():
    for budget in (0.0, -1 / 30, math.inf, math.nan, "fast"):
        with pytest.raises(ValueError, match="frame_budget must be a positive number of seconds"):
            RefinementSchedule(frame_budget=budget)
    with pytest.raises(ValueError, match="raise max_downscale or lower moving"):
        RefinementSchedule(moving=16)
    with pytest.raises(ValueError, match="integer downscale"):
        RefinementSchedule(moving=2.5)
    schedule = RefinementSchedule()
    with pytest.raises(ValueError, match="render_seconds must be a finite number of seconds"):
        schedule.record(4, -0.01)
    with pytest.raises(ValueError, match="level must be the integer downscale"):
        schedule.record(0, 0.01)


def test_view_rays_are_made_again_only_when_the_view_changes(device):
    """A still camera gets the very same device tensors back (the renderer then keeps their encoding too); a moved
    camera, other intrinsics, another view or another grid size get fresh rays, equal to the cameras' own."""
    cameras = scene_cameras("teapot", views=2, resolution=16)
    rays = ViewRays()

    def check(got, cameras, view, width, height):
        expected = cameras.grid_rays(view, width, height)
        for tensor, reference in zip(got, expected, strict=True):
            assert tensor.dtype == torch.float32 and tensor.is_contiguous() and tensor.device.type == device
            assert torch.equal(tensor.cpu(), reference.float())

    first = rays(cameras, 0, 8, 6)
    check(first, cameras, 0, 8, 6)
    assert all(a is b for a, b in zip(rays(cameras, 0, 8, 6), first, strict=True)), "a still camera: same tensors"
    copy = dataclasses.replace(cameras, c2w=cameras.c2w.clone(), fx=cameras.fx.clone())
    assert rays(copy, 0, 8, 6)[1] is first[1], "equal cameras in other tensors are still the same view"

    c2w = cameras.c2w.clone()
    c2w[0, 0, 3] += 0.01
    moved = dataclasses.replace(cameras, c2w=c2w)
    zoomed = dataclasses.replace(cameras, fx=cameras.fx * 1.5)
    for changed, view, width, height in ((moved, 0, 8, 6), (zoomed, 0, 8, 6), (cameras, 1, 8, 6), (cameras, 0, 4, 3)):
        got = rays(changed, view, width, height)
        assert got[0] is not first[0] and got[1] is not first[1]
        check(got, changed, view, width, height)
    assert rays(cameras, 0, 8, 6)[1] is not first[1], "only the last view's rays are kept"


def test_a_still_camera_renders_the_nerf_without_encoding_its_rays_again(device, monkeypatch):
    field = MeshAlbedoField("teapot")
    particles = grid_sample(scene_density("teapot"), 0.06)
    model = QGMLSModel.from_particles(particles, DiscretizationConfig(kernel_count=8))
    preview = NerfRenderBackend(field, field.occupancy_grid(32), model, downscale=2)
    calls = []
    encode = field.encode_directions
    monkeypatch.setattr(field, "encode_directions", lambda d: calls.append(d) or encode(d))
    cameras = scene_cameras("teapot", views=2, resolution=24)
    q = torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device)
    first = preview.render(q, cameras, 0)
    assert len(calls) == 1 and first.rgba.shape == (24, 24, 4) and float(first.rgba[..., 3].max()) > 0.5
    dragged = preview.render(q + 0.01, cameras, 0)
    again = preview.render(q, cameras, 0)
    assert len(calls) == 1, "the still camera's rays were encoded again"
    assert torch.equal(again.rgba, first.rgba) and torch.equal(again.depth, first.depth)
    assert not torch.equal(dragged.rgba, first.rgba)
    preview.render(q, cameras, 1)
    assert len(calls) == 2, "another view must be encoded"
