"""The colliders of a scenario at a time: the floor and the ``[[colliders]]``, keyframed planes moved."""

from __future__ import annotations

from pienerf.scenario.keyframes import keyframe
from pienerf.scenario.schema import ScenarioError
from pienerf.sim.solver import PlaneCollider, SphereCollider

__all__ = ["scenario_colliders"]


def scenario_colliders(scenario: dict, t: float, floor: bool) -> list[PlaneCollider | SphereCollider]:
    """The floor (when on) and the ``[[colliders]]`` at time ``t`` (s), keyframed planes moved."""
    colliders = [PlaneCollider()] if floor else []
    for i, spec in enumerate(scenario.get("colliders", [])):
        kind = spec.get("type")
        if kind == "plane":
            point = spec.get("point", [0.0, 0.0, 0.0])
            if "keys" in spec:
                point = keyframe(spec["keys"], t, f"colliders[{i}].keys").tolist()
            colliders.append(PlaneCollider(tuple(point), tuple(spec.get("normal", [0.0, 1.0, 0.0]))))
        elif kind == "sphere":
            if "centre" not in spec or "radius" not in spec:
                raise ScenarioError(f"'colliders[{i}]' sphere needs 'centre' and 'radius'")
            colliders.append(SphereCollider(tuple(spec["centre"]), float(spec["radius"])))
        else:
            raise ScenarioError(f"'colliders[{i}].type' must be 'plane' or 'sphere', got {kind!r}")
    return colliders
