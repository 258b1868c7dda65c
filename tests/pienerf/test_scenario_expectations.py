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
