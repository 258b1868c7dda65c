"""resolve_intersections: a garment that starts inside the body, or through itself, made simulable.

Distances and winding numbers are checked against the brute-force float64 references of :mod:`kernels.reference`
(every triangle measured), not the module's own accelerated queries.
"""

import math

import numpy as np
import pytest
import torch
import trimesh

from kernels import backend
from kernels.reference.raycast import closest_points, winding_number
from physavatar.cloth import ClothConfig, ClothControl, SolverCloth, garment_distances
from physavatar.intersections import RELAX_RINGS, resolve_intersections

F64 = torch.float64
EPS = torch.finfo(F64).eps
GAP = 1.5 * ClothConfig().contact_distance + 1e-4  # what a caller passes: above the barrier's reach d̂


def _sphere(radius: float, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    mesh.apply_translation(centre)
    return mesh


def _tensors(mesh: trimesh.Trimesh) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(mesh.vertices, dtype=F64), torch.tensor(mesh.faces, dtype=torch.int64)


def _grid_faces(rows: int, columns: int, closed: bool) -> torch.Tensor:
    """Triangles of a ``rows × columns`` vertex grid (index ``i · columns + j``), rows joined last to first when
    ``closed`` (a tube)."""
    faces = []
    for i in range(rows if closed else rows - 1):
        for j in range(columns - 1):
            a, b = i * columns + j, ((i + 1) % rows) * columns + j
            faces += [[a, b, a + 1], [b, b + 1, a + 1]]
    return torch.tensor(faces, dtype=torch.int64)


def _tube(radius: float, around: int, along: int, start: float, end: float, axis: int) -> tuple[torch.Tensor, ...]:
    """An open cylinder of ``around × along`` vertices about the coordinate ``axis``, from ``start`` to ``end``."""
    angle = torch.arange(around, dtype=F64) * (2.0 * math.pi / around)
    height = torch.linspace(start, end, along, dtype=F64)
    a, h = torch.meshgrid(angle, height, indexing="ij")
    columns = [radius * torch.cos(a), radius * torch.sin(a)]
    columns.insert(axis, h)
    return torch.stack(columns, -1).reshape(-1, 3), _grid_faces(around, along, closed=True)


def _tolerance(*points: torch.Tensor) -> float:
    """The rounding of a closest-point distance in the scene: 128 ε times its bounding-box diagonal."""
    everything = torch.cat(points)
    return 128 * EPS * float(torch.linalg.vector_norm(everything.amax(0) - everything.amin(0)))


def _within_rings(faces: torch.Tensor, seeds: torch.Tensor, count: int, vertex_count: int) -> torch.Tensor:
    near = torch.zeros(vertex_count, dtype=torch.bool)
    near[seeds] = True
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    for _ in range(count):
        step = near.clone()
        step[edges[near[edges[:, 0]], 1]] = True
        step[edges[near[edges[:, 1]], 0]] = True
        near = step
    return near


def test_vertices_pushed_into_a_sphere_come_out_to_the_gap_and_nothing_else_moves(device):
    body, body_faces = _tensors(_sphere(0.2))
    x, faces = _tube(0.205, 48, 8, -0.04, 0.04, axis=1)  # 5 mm outside the sphere's circumscribed ball
    generator = torch.Generator().manual_seed(7)
    offenders = torch.randperm(x.shape[0], generator=generator)[: x.shape[0] // 20]
    sink = 0.003 + 0.002 * torch.rand(offenders.numel(), generator=generator, dtype=F64)
    x[offenders] *= ((0.2 - sink) / torch.linalg.vector_norm(x[offenders], dim=1))[:, None]
    depth = closest_points(body, body_faces, x[offenders])
    assert bool((winding_number(body, body_faces, x[offenders]) > 0.5).all())  # inside the mesh, 2.4–5 mm deep

    y, report = resolve_intersections(x, faces, body, body_faces, GAP)

    tol = _tolerance(x, y, body)
    assert float(closest_points(body, body_faces, y).min()) >= GAP - tol
    assert float(winding_number(body, body_faces, y).max()) < 0.5
    assert report.inside_body == report.moved == offenders.numel()
    assert report.remaining_inside == report.self_remaining == report.edges_through_body == 0 and report.clear
    move = torch.linalg.vector_norm(y - x, dim=1)
    assert bool((move[offenders] <= depth + GAP + tol).all())  # closest point plus the gap, no farther
    assert report.max_move_m == pytest.approx(float(move.max()), abs=tol)
    assert report.max_move_m <= float((depth + GAP).max()) + tol
    assert report.mean_move_m == pytest.approx(float(move[offenders].mean()), abs=tol)
    near = _within_rings(faces, offenders, RELAX_RINGS, x.shape[0])
    assert torch.equal(y[~near], x[~near])  # beyond the relaxed rings: bit for bit as given
    followers = (move > 0) & ~_within_rings(faces, offenders, 0, x.shape[0])
    assert 0 < report.relaxed == int(followers.sum())
    assert float(move[followers].max()) <= float(move[offenders].max())
    assert report.summary().startswith(f"moved {offenders.numel()} of {x.shape[0]} garment vertices")


def test_an_arm_into_the_torso_every_vertex_ends_outside_both_parts(device):
    torso, arm = _sphere(0.1), _sphere(0.06, (0.12, 0.0, 0.0))  # the arm's end lies inside the torso
    body, body_faces = _tensors(trimesh.util.concatenate([torso, arm]))
    places = torch.tensor(
        [
            [0.08, 0.0, 0.0],  # inside both parts
            [0.085, 0.01, 0.005],  # inside both parts
            [-0.05, 0.0, 0.0],  # deep inside the torso
            [0.055, 0.0, 0.02],  # inside the torso only, nearest to the arm's buried surface
            [0.15, 0.0, 0.0],  # inside the arm only
            [0.12, 0.04, 0.0],  # inside the arm only
            [0.09, 0.045, 0.0],  # inside the arm, 0.6 mm outside the torso: in the crease
        ],
        dtype=F64,
    )
    corner = torch.tensor([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0]], dtype=F64)
    x = (places[:, None] + corner).reshape(-1, 3)  # a 1 mm triangle at each place
    faces = torch.arange(x.shape[0]).reshape(-1, 3)
    parts = [_tensors(torso), _tensors(arm)]
    buried = places[3:4]  # a push along its closest triangle's normal would lead further into the torso
    assert float(closest_points(*parts[1], buried)) < 0.25 * float(closest_points(*parts[0], buried))

    y, report = resolve_intersections(x, faces, body, body_faces, GAP)

    for part in parts:
        assert float(winding_number(*part, y).max()) < 0.5
    assert float(closest_points(body, body_faces, y).min()) >= GAP - _tolerance(x, y, body)
    assert report.inside_body == report.moved == x.shape[0] and report.clear


def _folded_strip(dip: float, width: float):
    """A 12 cm strip folded in half about a 2.5 mm radius, its upper layer 5 mm above the lower one and dipping by
    ``dip`` (a Gaussian of standard deviation ``width``, m) in the middle: through the lower layer where ``dip`` > 5
    mm."""
    length, breadth, radius, rows, columns = 0.06, 0.04, 0.0025, 40, 9
    arc = math.pi * radius
    u, v = np.meshgrid(np.linspace(0.0, 2 * length + arc, rows), np.linspace(0.0, breadth, columns), indexing="ij")
    fold = (u - length) / radius
    x = np.where(u <= length, u, np.where(u <= length + arc, length + radius * np.sin(fold), 2 * length + arc - u))
    z = np.where(u <= length, 0.0, np.where(u <= length + arc, radius * (1 - np.cos(fold)), 2 * radius))
    upper = u > length + arc
    z = z - np.where(upper, dip * np.exp(-((x - 0.03) ** 2 + (v - 0.02) ** 2) / (2 * width**2)), 0.0)
    points = torch.tensor(np.stack([x, v, z], -1).reshape(-1, 3), dtype=F64)
    return points, _grid_faces(rows, columns, closed=False)


def _crossings(x: torch.Tensor, faces: torch.Tensor) -> int:
    """Edge–triangle pairs sharing no vertex whose edge meets the triangle (Möller–Trumbore on every pair)."""
    edges = torch.unique(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).sort(1).values, dim=0)
    p, d = x[edges[:, 0]][:, None], (x[edges[:, 1]] - x[edges[:, 0]])[:, None]
    a, b, c = (x[faces[:, k]][None] for k in range(3))
    e1, e2 = b - a, c - a
    h = torch.linalg.cross(d, e2)
    det = (e1 * h).sum(-1)
    inv = 1.0 / det
    s = p - a
    u = (s * h).sum(-1) * inv
    q = torch.linalg.cross(s, e1)
    v = (d * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    hit = (det.abs() > 1e-18) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    shared = (edges[:, None, :, None] == faces[None, :, None, :]).any(-1).any(-1)
    return int((hit & ~shared).sum())


def test_a_layer_dipping_through_the_other_is_separated(device):
    x, faces = _folded_strip(dip=0.007, width=0.004)
    far_body, far_faces = _tensors(_sphere(0.02, (0.03, 0.02, -0.1)))  # 10 cm below: the garment against itself
    assert _crossings(x, faces) > 0

    y, report = resolve_intersections(x, faces, far_body, far_faces, GAP)

    assert report.self_intersecting > 0 and report.self_remaining == 0 and report.inside_body == 0
    assert _crossings(y, faces) == 0
    assert report.clear and report.moved > 0 and report.max_move_m < 0.007  # less than the dip: a local repair


def test_sheets_crossing_over_their_whole_width_are_reported_not_tangled_further(device):
    s = torch.linspace(0.0, 0.04, 10, dtype=F64)
    u, v = torch.meshgrid(s, s, indexing="ij")
    flat = torch.stack([u, v, torch.zeros_like(u)], -1).reshape(-1, 3)
    tilted = torch.stack([u + 1e-3, v + 1.3e-3, 0.2 * (u - 0.02)], -1).reshape(-1, 3)  # through the flat one
    grid = _grid_faces(10, 10, closed=False)
    x, faces = torch.cat([flat, tilted]), torch.cat([grid, grid + 100])
    body, body_faces = _tensors(_sphere(0.02, (0.02, 0.02, -0.1)))

    y, report = resolve_intersections(x, faces, body, body_faces, GAP)

    assert 0 < report.self_remaining <= report.self_intersecting and not report.clear
    assert "LEFT" in report.summary() and f"{report.self_remaining} on crossing triangles" in report.summary()
    assert _crossings(y, faces) > 0
    assert float(closest_points(body, body_faces, y).min()) >= GAP


def test_a_garment_already_clear_is_returned_unchanged(device):
    body, body_faces = _tensors(_sphere(0.2))
    x, faces = _tube(0.21, 24, 5, -0.03, 0.03, axis=1)
    assert float(closest_points(body, body_faces, x).min()) > GAP
    y, report = resolve_intersections(x, faces, body, body_faces, GAP)
    assert torch.equal(y, x) and y.dtype == F64
    assert report.moved == report.inside_body == report.self_intersecting == report.relaxed == 0
    assert report.max_move_m == report.mean_move_m == 0.0 and report.clear
    assert "nothing moved" in report.summary()


def test_bad_input_raises_naming_the_fix(device):
    body, body_faces = _tensors(_sphere(0.2))
    x, faces = _tube(0.21, 12, 3, -0.03, 0.03, axis=1)
    nan = x.clone()
    nan[5, 1] = math.nan
    cases = [
        ((x[:, :2], faces, body, body_faces, GAP), r"garment_vertices must be a float \[N, 3\].*one row \(x, y, z\)"),
        ((x, faces.double(), body, body_faces, GAP), r"garment_faces must be an integer \[F, 3\]"),
        ((x, faces + 100, body, body_faces, GAP), r"garment_faces index vertices .* pass faces that index"),
        ((nan, faces, body, body_faces, GAP), r"NaN or inf \(e\.g\. vertex 5\); repair or drop"),
        ((x, faces, body[:, None], body_faces, GAP), r"body_vertices must be a float \[N, 3\]"),
        ((x, faces, body, body_faces[:0], GAP), r"body_faces must be .* at least one triangle"),
        ((x, faces, body, body_faces, 0.0), r"gap must be a positive clearance .* contact distance"),
        ((x, faces, body, body_faces, -1e-3), r"gap must be a positive"),
        ((x, faces, body, body_faces, math.nan), r"gap must be a positive"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            resolve_intersections(*args)
    with pytest.raises(ValueError, match="iterations must be an integer of at least 1"):
        resolve_intersections(x, faces, body, body_faces, GAP, iterations=0)


# --- the simulator starts from the result --------------------------------------------------------------------


def _step_twice(x: torch.Tensor, faces: torch.Tensor, body: torch.Tensor, body_faces: torch.Tensor):
    solver = SolverCloth(x, faces, ClothConfig(), body_faces)
    device = backend.torch_device()
    held = body.to(device)
    control = ClothControl(held, held, torch.zeros(0, dtype=torch.int64, device=device), held[:0])
    state = solver.initial_state()
    reports = [solver.step(state, state, control, 0.04) for _ in range(2)]
    return state.x.cpu(), reports


def test_the_simulator_steps_a_garment_resolved_out_of_a_sphere(device):
    body, body_faces = _tensors(_sphere(0.2))
    x, faces = _tube(0.203, 24, 4, -0.03, 0.03, axis=1)
    x[::7] *= 0.196 / 0.203  # every 7th vertex 4 mm into the sphere
    with pytest.raises(ValueError, match="start inside the body collider"):
        _step_twice(x, faces, body, body_faces)

    y, report = resolve_intersections(x, faces, body, body_faces, GAP)
    assert report.clear and report.moved == len(range(0, x.shape[0], 7))
    end, reports = _step_twice(y, faces, body, body_faces)

    assert all(r.min_distance_body > 0.0 and r.min_distance_self > 0.0 for r in reports)
    assert float(winding_number(body, body_faces, end).max()) < 0.5
    assert garment_distances(end, faces, body, body_faces).inside == 0


def test_the_simulator_steps_a_sheet_resolved_out_of_an_arm_into_the_torso(device):
    """The body intersects itself; the simulator still steps it: pairs of body primitives are never contacts."""
    torso, arm = _sphere(0.1), _sphere(0.06, (0.12, 0.0, 0.0))  # they meet on a circle at x = 0.087 m, radius 0.05
    body, body_faces = _tensors(trimesh.util.concatenate([torso, arm]))
    u, v = torch.meshgrid(
        torch.linspace(0.05, 0.15, 9, dtype=F64), torch.linspace(-0.02, 0.02, 5, dtype=F64), indexing="ij"
    )
    x = torch.stack([u, torch.full_like(u, 0.045), v], -1).reshape(-1, 3)  # through both, across their crease
    faces = _grid_faces(9, 5, closed=False)
    parts = [_tensors(torso), _tensors(arm)]
    inside = [winding_number(*part, x) > 0.5 for part in parts]
    assert bool((inside[0] & inside[1]).any()) and bool((inside[0] ^ inside[1]).any())

    y, report = resolve_intersections(x, faces, body, body_faces, GAP)
    assert report.clear and report.moved == int((inside[0] | inside[1]).sum())
    end, reports = _step_twice(y, faces, body, body_faces)

    assert all(r.min_distance_body > 0.0 for r in reports)
    for part in parts:
        assert float(winding_number(*part, end).max()) < 0.5
