"""A scenario's ``[expect]`` table: what its run must show, checked against the run's metrics.

A scripted figure states the physics it shows, so a run that stops showing it fails instead of rendering a wrong
figure quietly. Every key is optional; a variant's own ``expect`` table overrides the scenario's key by key:

* ``relative_volume = [low, high]``: the body's final volume over its rest volume;
* ``max_displacement_m = [low, high]``: the final largest particle displacement (m);
* ``centre_displacement_m = [low, high]``: the final displacement of the particles' mean position (m);
* ``converged_fraction = f``: at least this fraction of the steps met the Newton tolerance;
* ``warp_psnr_db = p``: each warped-NeRF mode's mean PSNR against the mesh (``[warp_error]``) is at least ``p`` dB;
* ``warp_psnr_gain_db = g``: the quadratic warp's mean PSNR exceeds the linear warp's by at least ``g`` dB.

The two warp keys hold for the full run only (a full-size NeRF, the whole deformation): :data:`FULL_RUN_KEYS` are
dropped from a smoke run and a run shortened by ``--frames`` (:func:`pienerf.scenario.load_scenario`).

A run whose solver result is wrong (:meth:`pienerf.scenario.StepTally.wrong_result`) fails every expectation it has.
"""

from __future__ import annotations

__all__ = ["EXPECT_KEYS", "FULL_RUN_KEYS", "check_expectations", "failed_lines"]

EXPECT_KEYS = {
    "relative_volume": "final volume / rest volume",
    "max_displacement_m": "final largest particle displacement (m)",
    "centre_displacement_m": "final displacement of the particles' mean position (m)",
    "converged_fraction": "fraction of steps that met the Newton tolerance",
    "warp_psnr_db": "mean PSNR of each warped-NeRF mode against the mesh (dB)",
    "warp_psnr_gain_db": "mean PSNR of the quadratic warp minus the linear warp's (dB)",
}
"""The keys of an ``[expect]`` table and what each bounds."""

FULL_RUN_KEYS = ("warp_psnr_db", "warp_psnr_gain_db")
"""Keys whose bounds were measured on the full-size run: a smoke NeRF and a shortened deformation do not meet them."""


def _measured(key: str, variant: dict) -> list[tuple[str, float | None]]:
    """``(what, value)`` pairs a key bounds in one variant's metrics (several for ``warp_psnr_db``: one per mode)."""
    if key == "relative_volume":
        return [(key, variant["final_relative_volume"])]
    if key == "max_displacement_m":
        return [(key, variant["final_max_displacement_m"])]
    if key == "centre_displacement_m":
        return [(key, variant["final_centre_displacement_m"])]
    if key == "converged_fraction":
        solver = variant["solver"]
        return [(key, 1.0 - solver["unconverged_steps"] / solver["steps"] if solver["steps"] else 1.0)]
    modes = variant.get("warp_error", {}).get("modes", {})
    if key == "warp_psnr_gain_db":
        if "nerf" not in modes or "nerf_linear" not in modes:
            return [(key, None)]
        return [(key, modes["nerf"]["mean_psnr_db"] - modes["nerf_linear"]["mean_psnr_db"])]
    return [(f"{key} ({mode})", entry["mean_psnr_db"]) for mode, entry in modes.items()] or [(key, None)]


def check_expectations(scenario: dict, variants: dict) -> dict | None:
    """Check each variant's metrics (``{name: run_metrics(...)}``, :func:`pienerf.scenario.run_metrics`) against the
    scenario's ``[expect]`` table over each variant's own ``expect``; ``None`` when neither holds a key.

    Returns:
        ``{"passed": bool, "checks": [{"variant", "key", "value", "expected", "passed"}, ...]}``; ``expected`` is
        ``[low, high]`` for a band, ``[low, null]`` for a lower bound.
    """
    own = {v.get("name", "default"): v.get("expect", {}) for v in scenario.get("variants", [])}
    checks = []
    for name, metrics in variants.items():
        expect = {**scenario.get("expect", {}), **own.get(name, {})}
        wrong = metrics["solver"].get("wrong_result")
        for key, bound in expect.items():
            low, high = (bound[0], bound[1]) if isinstance(bound, list) else (bound, None)
            for what, value in _measured(key, metrics):
                passed = (
                    not wrong
                    and value is not None
                    and value >= low
                    and (high is None or value <= high)
                )
                checks.append({"variant": name, "key": what, "value": value, "expected": [low, high], "passed": passed})
    if not checks:
        return None
    return {"passed": all(check["passed"] for check in checks), "checks": checks}


def failed_lines(expectations: dict | None) -> list[str]:
    """One line per failed check, e.g. ``variant 'arap': relative_volume = 0.71, expected in [0.9, 1.1]``."""
    lines = []
    for check in (expectations or {}).get("checks", []):
        if not check["passed"]:
            low, high = check["expected"]
            bound = f"in [{low:g}, {high:g}]" if high is not None else f">= {low:g}"
            value = "none" if check["value"] is None else f"{check['value']:.4g}"
            lines.append(f"variant {check['variant']!r}: {check['key']} = {value}, expected {bound}")
    return lines
