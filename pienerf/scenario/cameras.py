"""The cameras of a scenario's ``[cameras]`` table at a time: an orbit (that may spin) or fixed positions."""

from __future__ import annotations

from dataclasses import replace

import torch

from pienerf.nerf.cameras import Cameras, look_at_cameras, orbit_cameras
from pienerf.scenario.schema import ScenarioError

__all__ = ["scenario_cameras"]


def scenario_cameras(scenario: dict, centre, t: float) -> Cameras:
    """The ``[cameras]`` table at time ``t`` (s): an orbit about ``centre [3]`` (m), turning at ``spin_deg_per_s``,
    or fixed positions looking at one point.

    ``up`` (default +y) is the world direction shown upright: elevations and azimuths are measured from and about
    it, so a scenario whose gravity points along −z sets ``up = [0, 0, 1]`` to be seen the right way up.
    """
    spec = scenario["cameras"]
    width, height, fov = spec.get("width", 320), spec.get("height", 240), spec.get("fov", 40.0)
    kind = spec.get("type", "orbit")
    turn = _up_rotation(spec.get("up", [0.0, 1.0, 0.0]))  # from a y-up frame to the world
    if kind == "orbit":
        spin = spec.get("spin_deg_per_s", 0.0) * t
        azimuths = [a + spin for a in spec.get("azimuths", [0.0])]
        local_centre = turn.T @ torch.as_tensor(centre, dtype=torch.float64).reshape(3)
        cameras = orbit_cameras(
            local_centre, spec.get("distance", 2.5), azimuths, spec.get("elevation", 15.0), width, height, fov
        )
    elif kind == "fixed":
        if "positions" not in spec or "look_at" not in spec:
            raise ScenarioError("fixed cameras need 'cameras.positions' ([[x, y, z], ...]) and 'cameras.look_at'")
        positions = torch.tensor(spec["positions"], dtype=torch.float64) @ turn
        look_at = turn.T @ torch.tensor(spec["look_at"], dtype=torch.float64)
        cameras = look_at_cameras(positions, look_at.expand_as(positions), width, height, fov)
    else:
        raise ScenarioError(f"'cameras.type' must be 'orbit' or 'fixed', got {kind!r}")
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3] = turn
    return replace(cameras, c2w=(transform @ cameras.c2w.double()).float())


def _up_rotation(up) -> torch.Tensor:
    """The ``[3, 3]`` rotation taking +y to the unit vector of ``up`` (the shortest turn; a half turn about x for
    −y)."""
    target = torch.tensor(up, dtype=torch.float64)
    norm = float(target.norm())
    if norm == 0.0:
        raise ScenarioError("'cameras.up' must be a non-zero direction like [0.0, 1.0, 0.0]")
    target = target / norm
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    axis, cosine = torch.linalg.cross(y, target), float(y @ target)
    if cosine < -1.0 + 1e-12:
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    k = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], dtype=torch.float64
    )
    return torch.eye(3, dtype=torch.float64) + k + k @ k / (1.0 + cosine)
