"""Range, unit and meaning of a config dataclass's field, kept on the field itself.

A config field declared with :func:`setting` carries its unit, its allowed range and its choices in the field's
metadata, so that whatever reads settings from outside (the TOML scenarios of :mod:`pienerf.scenario`) checks them
against the one declaration instead of repeating the ranges:

    young_modulus: float = setting(1.0e5, unit="Pa", low=0.0, high=1e12, low_open=True, doc="Young's modulus E")

:func:`setting_range` reads it back as a :class:`SettingRange`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

__all__ = ["SettingRange", "setting", "setting_range"]

_KEY = "setting"


@dataclass(frozen=True)
class SettingRange:
    """What a setting may be: its kind (``int`` or ``float``, or ``str`` with ``choices``), its closed or open range,
    its unit and a short description.

    Attributes:
        kind: ``int``, ``float`` or ``str``.
        low, high: the range's ends (``None``: unbounded).
        unit: SI unit, ``""`` for a pure number.
        low_open: the low end is excluded (``low < value``).
        choices: the allowed strings of a ``str`` setting.
        doc: what the setting is.
    """

    kind: type
    low: float | None = None
    high: float | None = None
    unit: str = ""
    low_open: bool = False
    choices: tuple[str, ...] = ()
    doc: str = ""

    def describe(self) -> str:
        """The range in words, e.g. ``a number in (0, 1e+12] Pa`` or ``one of neo_hookean, arap``."""
        if self.kind is str:
            return f"one of {', '.join(self.choices)}"
        kind = "an integer" if self.kind is int else "a number"
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        bracket = "(" if self.low_open or self.low is None else "["
        unit = f" {self.unit}" if self.unit else ""
        return f"{kind} in {bracket}{low}, {high}{']' if self.high is not None else ')'}{unit}"

    def admits(self, value) -> bool:
        """Whether ``value`` is of the kind, finite and in the range (or one of the choices)."""
        if self.kind is str:
            return isinstance(value, str) and (not self.choices or value in self.choices)
        if isinstance(value, bool) or not isinstance(value, (int, float) if self.kind is float else int):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and not (self.low < value if self.low_open else self.low <= value):
            return False
        return self.high is None or value <= self.high


def setting(
    default=dataclasses.MISSING,
    *,
    unit: str = "",
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    choices=(),
    kind: type | None = None,
    doc: str = "",
):
    """A dataclass field with ``default`` whose metadata holds its :class:`SettingRange`; ``kind`` defaults to the
    default's type (``float`` where the default is ``None``)."""
    if kind is None:
        kind = type(default) if isinstance(default, (int, float, str)) and not isinstance(default, bool) else float
    spec = SettingRange(kind, low, high, unit, low_open, tuple(choices), doc)
    return dataclasses.field(default=default, metadata={_KEY: spec})


def setting_range(cls, name: str) -> SettingRange:
    """The :class:`SettingRange` of field ``name`` of dataclass ``cls``.

    Raises:
        KeyError: ``cls`` has no such field, or it was not declared with :func:`setting`.
    """
    for field in dataclasses.fields(cls):
        if field.name == name:
            if _KEY not in field.metadata:
                raise KeyError(f"{cls.__name__}.{name} is not declared with pienerf.sim.settings.setting")
            return field.metadata[_KEY]
    raise KeyError(f"{cls.__name__} has no field {name!r}")
