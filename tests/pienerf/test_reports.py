import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from kernels import backend
from pienerf.reports import TimeBreakdown, VolumeHistory, plot_time_breakdown, plot_volume_bars
from pienerf.sim.materials import Material
from pienerf.sim.solver import QGMLSControl, SolverConfig, SolverQGMLS
from tests.pienerf.sim.test_solver import box_model


def test_time_breakdown_and_volume_reports_are_written(device, tmp_path):
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(), SolverConfig(newton_iterations=2))
    state, breakdown = solver.rest_state(), TimeBreakdown()
    history = VolumeHistory(rest_volume=float(model.volume.sum()))
    for i in range(3):
        breakdown.add(solver.step(state, state, QGMLSControl(), 1e-2))
        history.add(f"step {i}", float(model.deformed_volume(state.q)))
    breakdown.add_phase("warping", 0.001)
    assert breakdown.steps == 3 and breakdown.newton_iterations >= 3
    assert sum(breakdown.fractions().values()) == pytest.approx(1.0)
    pie = plot_time_breakdown(breakdown, tmp_path / "breakdown.png")
    data = json.loads(pie.with_suffix(".json").read_text())
    phases = {"assembly", "solve", "line search", "other", "warping"} | (
        {"device loop"} if model.device.type == "cuda" else set())
    assert data["steps"] == 3 and set(data["fractions"]) == phases  # CUDA's device loop is timed as a whole
    assert iio.imread(pie).shape[2] in (3, 4)
    assert history.relative() == pytest.approx([1.0, 1.0, 1.0], abs=1e-9)  # free fall keeps the volume
    squashed = VolumeHistory(1.0, ["10%", "40%"], [0.9, 0.6])
    bars = plot_volume_bars([("free fall", VolumeHistory(1.0, ["10%", "40%"], [1.0, 1.0])), ("arap", squashed)],
                            tmp_path / "volume.png")
    assert json.loads(bars.with_suffix(".json").read_text())["arap"]["relative_volume"] == [0.9, 0.6]
    assert iio.imread(bars).ndim == 3
    assert torch.isfinite(state.q).all()


def bar_pixels(path) -> list[int]:
    """Pixels of matplotlib's first and second default colours (the bars of the first and second run)."""
    image = iio.imread(path)[..., :3].astype(int)
    return [int((np.abs(image - colour).sum(-1) < 12).sum()) for colour in ((31, 119, 180), (255, 127, 14))]


def test_volume_bars_draw_a_bar_per_sample_and_say_when_there_are_none(tmp_path):
    histories = [
        ("neo_hookean", VolumeHistory(1.0, ["t = 1 s"], [0.98])),
        ("arap", VolumeHistory(1.0, ["t = 1 s"], [0.7])),
    ]
    first, second = bar_pixels(plot_volume_bars(histories, tmp_path / "bars.png"))
    assert first > 1000 and second > 500  # a 0.98 bar and a 0.7 one, at 720 × 420 pixels
    empty = plot_volume_bars([("arap", VolumeHistory(1.0))], tmp_path / "empty.png")
    assert bar_pixels(empty) == [0, 0]
    image = iio.imread(empty)[..., :3].sum(-1)
    h, w = image.shape
    middle = image[h // 2 - 10 : h // 2 + 10, int(0.3 * w) : int(0.7 * w)]
    assert (middle < 200).sum() > 50  # the sentence saying why there are no bars, in the middle of the axes
    with pytest.raises(ValueError, match="at least one"):
        plot_volume_bars([], tmp_path / "none.png")


def test_time_breakdown_splits_timed_device_loop_steps_by_phase(device):
    """A device-loop step timed by phase adds to the four step phases, its time outside them to 'other', so that the
    phases sum to its wall time; an untimed one adds its whole time to 'device loop'."""
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(), SolverConfig(newton_iterations=2, device_loop=True))
    state = solver.rest_state()
    timed, untimed = TimeBreakdown(), TimeBreakdown()
    report = solver.step(state, state, QGMLSControl(), 1e-2, timed=True)
    timed.add(report)
    assert set(timed.seconds) == set(TimeBreakdown.STEP_PHASES) and all(v > 0 for v in timed.seconds.values())
    total = sum(timed.seconds.values())
    assert total == pytest.approx(report.time_device_loop, rel=4 * np.finfo(np.float64).eps)
    report = solver.step(state, state, QGMLSControl(), 1e-2)
    untimed.add(report)
    assert untimed.seconds["device loop"] == report.time_device_loop
    assert sum(untimed.seconds[name] for name in TimeBreakdown.STEP_PHASES) == 0
