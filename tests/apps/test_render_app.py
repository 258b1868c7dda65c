"""apps.render: every scenario of assets/scenarios renders at --smoke size and writes its outputs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from apps import render

SCENARIOS = sorted((Path(__file__).resolve().parents[2] / "assets" / "scenarios").glob("*.toml"))


def test_the_paper_figures_have_scenarios():
    names = {path.stem for path in SCENARIOS}
    assert {"plant_sway", "lego", "jelly_compression", "sculpture_cut", "teapot_rod", "cloth_sphere",
            "time_breakdown"} <= names


@pytest.mark.parametrize("scenario", SCENARIOS, ids=lambda path: path.stem)
def test_scenario_renders_at_smoke_size(device, scenario, tmp_path):
    out = tmp_path / scenario.stem
    assert render.main([str(scenario), "--out", str(out), "--smoke", "--device", device]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    if "skipped" in metrics:
        assert scenario.stem == "lego"
        assert "pienerf.render" in metrics["skipped"] or "absent" in metrics["skipped"]
        return
    spec = render.load_scenario(scenario, smoke=True)
    frames = spec["solver"]["frames"] + 1
    outputs = {"frames": True, "mp4": True, "depth": False, "shadow": False, **spec.get("outputs", {})}
    assert metrics["frames"] == frames and (out / "time_breakdown.png").is_file()
    variants = max(len(spec.get("variants", [])), 1)
    breakdown = metrics["time_breakdown"]
    assert breakdown["steps"] == (frames - 1) * variants and breakdown["newton_iterations"] > 0
    if outputs["frames"]:
        assert len(list((out / "frames").glob("frame_*.png"))) == frames
    if outputs["mp4"]:
        import imageio.v2 as imageio

        with imageio.get_reader(out / "video.mp4") as reader:
            assert reader.count_frames() == frames
    if outputs["depth"]:
        assert len(list((out / "depth").glob("*.npy"))) >= frames
    if outputs["shadow"]:
        assert len(list((out / "shadow").glob("*.png"))) >= frames
    if "volume_samples" in spec:
        assert (out / "volume_bars.png").is_file()
    for variant in metrics["variants"].values():
        assert 0.5 < variant["final_relative_volume"] < 1.5


def test_bad_scenarios_fail_with_one_line_naming_the_key(device, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "jelly"\n[material]\nyoungs_modulus = 1e4\n[cameras]\ntype = "orbit"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "material.youngs_modulus" in error and "young_modulus" in error
    bad.write_text('[scene]\nname = "jelly"\n[cameras]\nwidth = "wide"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "'cameras.width' must be an integer" in capsys.readouterr().err
    bad.write_text('[scene]\nname = "jelly"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "missing table [cameras]" in capsys.readouterr().err
