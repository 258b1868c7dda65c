"""pienerf.scenario.expectations: an [expect] table checked against a run's metrics, a variant's own over it."""

from __future__ import annotations

import pytest

from pienerf.scenario import ScenarioError, check_expectations, failed_lines, load_scenario


def _metrics(volume=1.0, largest=0.02, centre=0.01, unconverged=0, steps=10, wrong=None, psnr=None):
    metrics = {
        "final_relative_volume": volume,
        "final_max_displacement_m": largest,
        "final_centre_displacement_m": centre,
        "solver": {"steps": steps, "unconverged_steps": unconverged, "wrong_result": wrong},
    }
    if psnr is not None:
        metrics["warp_error"] = {"modes": {"nerf": {"mean_psnr_db": psnr}}}
    return metrics


def test_bands_and_floors_pass_inside_and_fail_outside():
    scenario = {"expect": {"relative_volume": [0.9, 1.1], "converged_fraction": 0.9, "warp_psnr_db": 20.0}}
    passed = check_expectations(scenario, {"default": _metrics(volume=0.95, unconverged=1, psnr=25.0)})
    assert passed["passed"] and len(passed["checks"]) == 3
    failed = check_expectations(scenario, {"default": _metrics(volume=0.8, unconverged=2, psnr=25.0)})
    assert [c["passed"] for c in failed["checks"]] == [False, False, True]
    assert failed_lines(failed) == [
        "variant 'default': relative_volume = 0.8, expected in [0.9, 1.1]",
        "variant 'default': converged_fraction = 0.8, expected >= 0.9",
    ]


def test_a_variant_overrides_the_scenario_key_by_key_and_a_wrong_result_fails():
    scenario = {
        "expect": {"relative_volume": [0.9, 1.1], "max_displacement_m": [0.0, 1.0]},
        "variants": [{"name": "arap", "expect": {"relative_volume": [0.5, 1.1]}}, {"name": "nh"}],
    }
    result = check_expectations(scenario, {"arap": _metrics(volume=0.7), "nh": _metrics(volume=0.7)})
    assert [(c["variant"], c["key"], c["passed"]) for c in result["checks"]] == [
        ("arap", "relative_volume", True),
        ("arap", "max_displacement_m", True),
        ("nh", "relative_volume", False),
        ("nh", "max_displacement_m", True),
    ]
    wrong = check_expectations(scenario, {"nh": _metrics(wrong="NaN")})
    assert not any(c["passed"] for c in wrong["checks"])
    assert check_expectations({}, {"nh": _metrics()}) is None


def test_a_missing_warp_error_fails_its_floor():
    result = check_expectations({"expect": {"warp_psnr_db": 10.0}}, {"default": _metrics()})
    assert not result["passed"] and result["checks"][0]["value"] is None


@pytest.mark.parametrize(
    ("table", "says"),
    [
        ("relative_volume = [1.1, 0.9]", "must list its low end first"),
        ("relative_volume = 0.9", "must be a band [low, high]"),
        ("converged_fraction = 1.5", "must be a number in [0, 1]"),
        ("volume = [0.9, 1.1]", "unknown key 'expect.volume'"),
    ],
)
def test_a_bad_expect_table_is_refused_by_key(tmp_path, table, says):
    path = tmp_path / "scenario.toml"
    path.write_text(f'[scene]\nname = "jelly"\n[cameras]\n[expect]\n{table}\n')
    with pytest.raises(ScenarioError, match=says.replace("[", r"\[").replace("]", r"\]")):
        load_scenario(path)


def test_smoke_expectations_replace_the_full_size_keys_at_smoke_size(tmp_path):
    path = tmp_path / "scenario.toml"
    path.write_text(
        '[scene]\nname = "jelly"\n[cameras]\n[expect]\nconverged_fraction = 0.9\nrelative_volume = [0.9, 1.1]\n'
        "[smoke]\nframes = 2\n[smoke.expect]\nconverged_fraction = 1.0\n"
    )
    assert load_scenario(path)["expect"] == {"converged_fraction": 0.9, "relative_volume": [0.9, 1.1]}
    assert load_scenario(path, smoke=True)["expect"] == {"converged_fraction": 1.0, "relative_volume": [0.9, 1.1]}
    assert load_scenario(path, smoke=True, frames=5)["expect"] == {
        "converged_fraction": 0.9,
        "relative_volume": [0.9, 1.1],
    }


def _warped(quadratic, linear):
    metrics = _metrics()
    metrics["warp_error"] = {"modes": {"nerf": {"mean_psnr_db": quadratic}, "nerf_linear": {"mean_psnr_db": linear}}}
    return metrics


def test_the_quadratic_warp_must_beat_the_linear_one_by_the_gain():
    scenario = {"expect": {"warp_psnr_gain_db": 2.0}}
    assert check_expectations(scenario, {"q": _warped(14.8, 11.0)})["passed"]
    failed = check_expectations(scenario, {"q": _warped(12.0, 11.0)})
    assert failed_lines(failed) == ["variant 'q': warp_psnr_gain_db = 1, expected >= 2"]
    assert not check_expectations(scenario, {"q": _metrics(psnr=20.0)})["passed"]  # no linear warp to compare


def test_full_run_bounds_are_dropped_from_smoke_and_shortened_runs(tmp_path):
    path = tmp_path / "scenario.toml"
    path.write_text(
        '[scene]\nname = "teapot"\n[cameras]\n[expect]\nconverged_fraction = 0.9\nwarp_psnr_db = 10.0\n'
        '[[variants]]\nname = "q"\nexpect = { warp_psnr_gain_db = 2.0, relative_volume = [0.5, 1.5] }\n'
        "[smoke]\nframes = 2\n"
    )
    full = load_scenario(path)
    assert full["expect"] == {"converged_fraction": 0.9, "warp_psnr_db": 10.0}
    assert full["variants"][0]["expect"] == {"warp_psnr_gain_db": 2.0, "relative_volume": [0.5, 1.5]}
    for short in (load_scenario(path, smoke=True), load_scenario(path, frames=4)):
        assert short["expect"] == {"converged_fraction": 0.9}
        assert short["variants"][0]["expect"] == {"relative_volume": [0.5, 1.5]}
