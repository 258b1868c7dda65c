"""pienerf.sim.settings: a config field carries its range, unit and choices; the scenario schema reads them."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import pytest

from pienerf.scenario import ScenarioError, load_scenario
from pienerf.sim.materials import MATERIAL_MODELS, Material
from pienerf.sim.picking import DragConfig
from pienerf.sim.settings import SettingRange, setting, setting_range


@dataclass(frozen=True)
class _Config:
    length: float = setting(1.0, unit="m", low=0.0, high=10.0, low_open=True, doc="a length")
    count: int = setting(3, low=1, high=5)
    plain: int = 0


def test_a_setting_keeps_its_default_and_reads_back_its_range():
    assert _Config().length == 1.0 and _Config.count == 3
    length = setting_range(_Config, "length")
    assert length == SettingRange(float, 0.0, 10.0, "m", True, (), "a length")
    assert length.describe() == "a number in (0, 10] m"
    assert [length.admits(v) for v in (0.0, 1e-9, 10.0, 10.5, math.nan, True, "1")] == [
        False,
        True,
        True,
        False,
        False,
        False,
        False,
    ]
    count = setting_range(_Config, "count")
    assert count.describe() == "an integer in [1, 5]" and count.admits(5) and not count.admits(2.0)
    with pytest.raises(KeyError, match="not declared with"):
        setting_range(_Config, "plain")
    with pytest.raises(KeyError, match="has no field 'missing'"):
        setting_range(_Config, "missing")


def test_config_fields_declare_the_ranges_the_scenarios_check(tmp_path):
    assert setting_range(Material, "model").choices == tuple(MATERIAL_MODELS)
    assert setting_range(DragConfig, "stiffness").unit == "N/m" and DragConfig().stiffness is None
    path = tmp_path / "scenario.toml"
    young = setting_range(Material, "young_modulus")
    path.write_text(f'[scene]\nname = "jelly"\n[cameras]\n[material]\nyoung_modulus = {young.high * 10:g}\n')
    with pytest.raises(ScenarioError, match=re.escape(f"'material.young_modulus' must be {young.describe()}")):
        load_scenario(path)
