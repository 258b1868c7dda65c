"""Rendering the deformed NeRF (PIE-NeRF §4.6, Fig. 7–8).

Every test renders :class:`pienerf.scenes.MeshAlbedoField` (the teapot's analytic density and mesh albedo, no
training), so that warping is judged without NeRF training noise: the ground truth of a deformation is the
teapot mesh deformed by the same Q-GMLS displacement and ray cast with its albedo.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from kernels import backend
from kernels.backend import FRAMEWORKS
from kernels.raycast import MeshBVH, shade
from kernels.volume_render import composite_forward, march_rays
from kernels.warp_rays import splat_occupancy, warp_to_rest
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.field import NGPConfig, NGPField, OccupancyGrid
from pienerf.render.deformed import DeformedRenderer, GroundPlane, bucket_size
from pienerf.scenes import MeshAlbedoField, scene_cameras, scene_density, scene_mesh
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.sampling import grid_sample
from pienerf.sim.solver import PointTargets, QGMLSControl, SolverConfig, SolverQGMLS

ROD_AXIS = (0.0, 0.2)  # (x, y) of the teapot's rod, which runs along +z from z = 0.12 m to 0.72 m
ROD_KERNELS = tuple((0.0, 0.2, z) for z in (0.35, 0.5, 0.62, 0.71))

_CACHE: dict = {}


def _teapot_model() -> QGMLSModel:
    """The teapot body sampled on a 3 cm grid, its 3 cm rod on a 1 cm lattice (9 particles per slice)."""
    particles = grid_sample(scene_density("teapot"), 0.03)
    body = particles.position.double().cpu()
    on_rod = ((body[:, 0] - ROD_AXIS[0]).abs() < 0.03) & ((body[:, 1] - ROD_AXIS[1]).abs() < 0.03) & (body[:, 2] > 0.2)
    body = body[~on_rod]
    offsets = torch.arange(-1, 2, dtype=torch.float64) * 0.01
    x, y, z = torch.meshgrid(offsets, offsets, torch.arange(0.125, 0.72, 0.01, dtype=torch.float64), indexing="ij")
    rod = torch.stack([x.flatten() + ROD_AXIS[0], y.flatten() + ROD_AXIS[1], z.flatten()], -1)
    position = torch.cat([body, rod])
    volume = torch.cat([torch.full((len(body),), 0.03**3), torch.full((len(rod),), 0.01**3)]).double()
    config = DiscretizationConfig(kernel_count=24, user_kernels=ROD_KERNELS)
    return QGMLSModel(position, volume, config, device=backend.torch_device())


def _bend(model: QGMLSModel) -> torch.Tensor:
    """Static equilibrium with the body pinned and the rod tip dragged 30 cm sideways (a large bend)."""
    solver = SolverQGMLS(model, Material(young_modulus=1e5, poisson_ratio=0.3), SolverConfig(gravity=(0.0, 0.0, 0.0)))
    body = model.position[model.position[:, 2] < 0.1][::25]
    pin = model.handle(body)
    tip = model.handle(model.position[model.position[:, 2] > 0.7])
    target = tip.rest + torch.tensor([0.3, 0.0, -0.1], dtype=torch.float64, device=model.device)
    control = QGMLSControl(springs=[PointTargets(pin, pin.rest.clone(), 1e4), PointTargets(tip, target, 1e3)])
    q, _ = solver.solve_static(control, iterations=6)
    return q


@pytest.fixture
def teapot(device):
    """Model, analytic field, renderer and the bent rod's q, built once per test process."""
    if "teapot" not in _CACHE:
        model = _teapot_model()
        field = MeshAlbedoField("teapot")
        renderer = DeformedRenderer(field, field.occupancy_grid(64), model)
        _CACHE["teapot"] = (model, field, renderer, _bend(model))
    return _CACHE["teapot"]


def _look_at(eye, target, up, resolution: int, fov: float = 0.5) -> Cameras:
    eye, target, up = (torch.tensor(v, dtype=torch.float32) for v in (eye, target, up))
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, torch.linalg.cross(right, forward), -forward, eye
    focal = torch.tensor([0.5 * resolution / math.tan(0.5 * fov)])
    centre = torch.tensor([0.5 * resolution])
    return Cameras(c2w[None], focal, focal.clone(), centre, centre.clone(), resolution, resolution)


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_zero_deformation_renders_the_undeformed_nerf(teapot, framework):
    """At q = 0 the warped render is the undeformed NeRF's: bit for bit with the Taichi kernels (the very march and
    compositing loops of :func:`pienerf.nerf.render_rays`); with the Warp kernels to float rounding (their ``exp``,
    and on CUDA their fused multiply-adds, may differ from Taichi's in the last bit)."""
    model, field, renderer, _ = teapot
    renderer = DeformedRenderer(field, renderer.grid, model, framework=framework)
    cameras = scene_cameras("teapot", views=4, resolution=200)
    q = torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device)
    rest = renderer.render(q, cameras, view=1, mode="rest", resolution=48)
    assert float(rest["alpha"].mean()) > 0.05, "the teapot must cover part of the view"
    for mode in ("quadratic", "linear"):
        warped = renderer.render(q, cameras, view=1, mode=mode, resolution=48)
        for key in ("rgb", "alpha", "depth"):
            if framework == "taichi":
                assert torch.equal(warped[key], rest[key]), f"{mode} warp at q = 0 changed {key}"
            torch.testing.assert_close(warped[key], rest[key], rtol=0.0, atol=1e-5, msg=f"{mode} warp, {key}")


def _full_march(renderer: DeformedRenderer, q: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor):
    """The straightforward render: one full march through the deformed grid, every sample warped and shaded, one
    composite. Returns premultiplied colour, opacity, ``Σ w t`` and the number of samples marched."""
    frame = renderer.frame(q)
    c = renderer.field.config
    samples = march_rays(
        origins, directions, 0.0, 1e10, frame.occupancy, frame.aabb, renderer.min_step, max_samples=c.max_samples
    )
    neighbours, distances = frame.ip_hash.knn(samples.positions, 3, max_radius=2.0 * float(renderer.cutoff.max()))
    warped = warp_to_rest(
        samples.positions,
        neighbours,
        distances,
        frame.ip_deformed,
        frame.ip_displacement,
        frame.F,
        frame.grad_F,
        renderer.cutoff,
    )
    keep = warped.valid & renderer.grid.is_occupied(warped.rest)
    sigma = torch.zeros(keep.shape[0], device=keep.device)
    rgb = torch.zeros(keep.shape[0], 3, device=keep.device)
    sigma[keep], rgb[keep] = renderer.field(warped.rest[keep], directions[samples.ray_indices][keep])
    color, opacity, depth, _, _ = composite_forward(
        sigma,
        rgb,
        samples.deltas,
        samples.depths,
        samples.ray_offsets,
        transmittance_threshold=c.transmittance_threshold,
    )
    return color, opacity, depth, samples.positions.shape[0]


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_rendering_in_rounds_matches_one_full_march(teapot, framework):
    """Rounds with early termination give the image of one full march and composite, for fewer samples; so do
    other round sizes and memory budgets, in either framework."""
    model, field, renderer, q = teapot
    renderer = DeformedRenderer(field, renderer.grid, model, framework=framework)
    cameras = scene_cameras("teapot", views=4, resolution=40)
    origins, directions = (t.to(backend.torch_device()).contiguous() for t in cameras.rays(1))
    color, opacity, depth, marched = _full_march(renderer, q, origins, directions)
    assert float(opacity.mean()) > 0.1, "the body must cover part of the view"
    black = (0.0, 0.0, 0.0)
    out = renderer.render(q, rays=(origins, directions), background=black)
    stats = renderer.stats
    atol = 1e-6 if framework == "taichi" else 1e-5  # the full march is Taichi's (test_zero_deformation_…)
    torch.testing.assert_close(out["rgb"], color, rtol=0.0, atol=atol)
    torch.testing.assert_close(out["alpha"], opacity, rtol=0.0, atol=atol)
    expected_depth = torch.where(opacity > 1e-6, depth / opacity.clamp_min(1e-6), 0.0)
    torch.testing.assert_close(out["depth"], expected_depth, rtol=0.0, atol=1e-5)
    assert 1 < stats.rounds < 20
    assert stats.samples_queried <= stats.samples_marched < 0.9 * marched, f"{stats} against {marched} marched"

    variants = (
        DeformedRenderer(field, renderer.grid, model, steps_per_round=3, round_samples=300, framework=framework),
        DeformedRenderer(field, renderer.grid, model, steps_per_round=128, framework=framework),
        DeformedRenderer(
            field,
            renderer.grid,
            model,
            first_round_steps=8,
            steps_per_round=128,
            round_samples=4096,
            framework=framework,
        ),
    )
    for variant in variants:
        again = variant.render(q, rays=(origins, directions), background=black)
        for key in ("rgb", "alpha", "depth"):
            torch.testing.assert_close(again[key], out[key], rtol=0.0, atol=1e-6)
    assert variants[0].stats.rounds > stats.rounds, "a small budget takes more rounds"
    assert variants[1].stats.rounds <= stats.rounds


def test_splat_marks_every_cell_the_moved_boxes_overlap(device):
    """The splat kernel marks exactly the cells a per-cell enumeration of each moved cell's box marks
    (at most 3 per axis, clipped to the grid), under a random smooth map, with boxes sticking out of the grid."""
    generator = torch.Generator().manual_seed(3)
    cell_size = torch.tensor([0.05, 0.04, 0.06], dtype=torch.float64)
    cells_lo = torch.randint(-2, 12, (300, 3), generator=generator).double() * cell_size
    ips = 7
    ip_rest = torch.rand(ips, 3, generator=generator, dtype=torch.float64) * 0.5
    displacement = 0.05 * torch.randn(ips, 3, generator=generator, dtype=torch.float64)
    F = torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(ips, 3, 3, generator=generator, dtype=torch.float64)
    grad_F = 2.0 * torch.randn(ips, 3, 3, 3, generator=generator, dtype=torch.float64)
    nearest = torch.randint(ips, (300,), generator=generator)
    aabb = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.4, 0.6]], dtype=torch.float64)
    shape = (10, 10, 10)
    inputs = (cells_lo, cell_size, nearest, ip_rest, displacement, F, grad_F, aabb)
    grid = splat_occupancy(*(t.to(backend.torch_device()) for t in inputs), shape).cpu()

    expected = torch.zeros(shape, dtype=torch.bool)
    deformed_cell = (aabb[1] - aabb[0]) / torch.tensor(shape)
    for c in range(300):
        k = int(nearest[c])
        corners = [
            cells_lo[c] + torch.tensor([i, j, m], dtype=torch.float64) * cell_size
            for i in (0, 1)
            for j in (0, 1)
            for m in (0, 1)
        ]
        moved = []
        for x in corners:
            d = x - ip_rest[k]
            moved.append(
                x
                + displacement[k]
                + (F[k] - torch.eye(3, dtype=torch.float64)) @ d
                + 0.5 * torch.einsum("abe,b,e->a", grad_F[k], d, d)
            )
        moved = torch.stack(moved)
        first = torch.floor((moved.amin(0) - aabb[0] + 1e-4 * deformed_cell) / deformed_cell).long()
        last = torch.minimum(
            torch.floor((moved.amax(0) - aabb[0] - 1e-4 * deformed_cell) / deformed_cell).long(), first + 2
        )
        for i in range(max(int(first[0]), 0), min(int(last[0]), shape[0] - 1) + 1):
            for j in range(max(int(first[1]), 0), min(int(last[1]), shape[1] - 1) + 1):
                for m in range(max(int(first[2]), 0), min(int(last[2]), shape[2] - 1) + 1):
                    expected[i, j, m] = True
    assert 0 < int(expected.sum()) < expected.numel(), "the case must mark some cells and leave others"
    assert torch.equal(grid, expected)


def _psnr(image: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> float:
    return -10.0 * math.log10(float(((image - truth) ** 2)[mask].mean()))


def test_quadratic_warping_beats_linear_on_the_bent_rod(teapot, record_property):
    """Fig. 8: against the deformed mesh's render, the quadratic warp's rod is closer than the linear warp's."""
    model, field, renderer, q = teapot
    tip_moved = model.handle(torch.tensor([[0.0, 0.2, 0.72]], dtype=torch.float64)).positions(q)[0, 0]
    assert float(tip_moved) > 0.25, "the rod tip must be dragged far sideways"

    resolution = 64
    cameras = _look_at((0.15, 2.0, 0.45), (0.15, 0.2, 0.45), (0.0, 0.0, -1.0), resolution)  # from above
    origins, directions = cameras.rays(0)
    device = backend.torch_device()
    mesh = field.mesh
    deformed = model.handle(mesh.vertices.double()).positions(q).float().to(device)
    bvh = MeshBVH(deformed, mesh.faces.to(device))
    origins, directions = origins.to(device), directions.to(device)
    truth = shade(bvh, origins, directions, mesh.colors.to(device), ambient=1.0, diffuse=0.0, shadows=False).rgba
    truth = truth[:, :3] + (1.0 - truth[:, 3:])  # albedo over the white background, as the renderer composites
    face = bvh.cast(origins, directions).face.long()
    rod = (face >= 0) & (mesh.part.to(device)[face.clamp_min(0)] == mesh.part_names.index("rod"))
    # The rod region: pixels of the true rod grown by 2 pixels, so a warp that misplaces the rod pays for both
    # the rod it misses and the background it covers, while the unchanged body does not dilute the score.
    mask = torch.nn.functional.max_pool2d(rod.float().view(1, 1, resolution, resolution), 5, 1, 2).flatten() > 0
    assert int(rod.sum()) > 50

    psnr = {}
    for mode in ("quadratic", "linear", "rest"):
        image = renderer.render(q, cameras, view=0, mode=mode)["rgb"].reshape(-1, 3)
        psnr[mode] = _psnr(image, truth, mask)
        psnr[mode + "_image"] = _psnr(image, truth, torch.ones_like(mask))
    for key, value in psnr.items():
        record_property(f"psnr_{key}_db", round(value, 2))
    assert psnr["quadratic"] > psnr["linear"], f"rod PSNR (dB): {psnr}"
    assert psnr["linear"] > psnr["rest"] + 1.0, f"any warp must beat ignoring the deformation: {psnr}"
    assert psnr["quadratic_image"] > psnr["rest_image"]


def test_shadow_on_the_ground_is_darker_under_the_object(teapot):
    """Fig. 7: a shadow map of transmittance toward the light darkens the ground under the teapot."""
    model, _, renderer, q = teapot
    ground = GroundPlane(extent=0.9, shadow_resolution=48)
    cameras = _look_at((-1.2, 1.6, -1.0), (0.0, 0.1, 0.1), (0.0, 1.0, 0.0), 48, fov=0.9)  # opposite the light
    out = renderer.render(q, cameras, view=0, ground=ground, background=(0.0, 0.0, 0.0))
    shadow_map = out["shadow_map"]
    assert shadow_map.shape == (48, 48)
    assert float(shadow_map.min()) < 0.05 and float(shadow_map.max()) == 1.0

    brightness = out["rgb"].mean(-1)
    uncovered = out["alpha"] < 0.01
    ground_seen = (brightness > 0) & uncovered  # the background is black
    shadowed = ground_seen & (out["ground_transmittance"] < 0.5)
    lit = ground_seen & (out["ground_transmittance"] == 1.0)
    assert int(shadowed.sum()) > 10 and int(lit.sum()) > 10, "the view must show shadowed and lit ground"
    assert float(brightness[shadowed].mean()) < 0.7 * float(brightness[lit].mean())
    lit_level = sum(ground.albedo) / 3 * (ground.ambient + ground.diffuse * _light_cosine(ground))
    assert abs(float(brightness[lit].mean()) - lit_level) < 1e-4


def test_encoded_directions_are_reused_while_the_rays_are_the_same(teapot, monkeypatch):
    """The camera rays' encoding is kept: the very same directions tensor, unchanged, is not encoded again; a change
    in place, another tensor or another field config is; the shadow map's rays neither reuse nor evict it; the
    images are the same either way."""
    model, field, renderer, q = teapot
    renderer = DeformedRenderer(field, renderer.grid, model)
    calls = []
    encode = field.encode_directions
    monkeypatch.setattr(field, "encode_directions", lambda d: calls.append(d) or encode(d))
    cameras = _look_at((-1.2, 1.6, -1.0), (0.0, 0.1, 0.1), (0.0, 1.0, 0.0), 24, fov=0.9)
    origins, directions = (t.to(backend.torch_device()).contiguous() for t in cameras.rays(0))
    frame = renderer.frame(q)

    def render(rays_directions, **kwargs):
        return renderer.render(q, rays=(origins, rays_directions), frame=frame, **kwargs)

    first = render(directions)
    assert len(calls) == 1 and calls[0] is directions
    again = render(directions)
    assert len(calls) == 1, "the same unchanged directions were encoded again"
    directions.mul_(1.0)  # written in place, the same values
    again_written = render(directions)
    assert len(calls) == 1, "directions written with their own values need no new encoding"
    directions.neg_()  # changed in place: another view through the same tensor
    render(directions)
    assert len(calls) == 2, "directions changed in place must be encoded again"
    directions.neg_()
    changed = render(directions)
    assert len(calls) == 3, "directions changed back in place must be encoded again"
    copy = directions.clone()
    other = render(copy)
    assert len(calls) == 4 and calls[3] is copy, "another tensor must be encoded"
    monkeypatch.setattr(field, "config", dataclasses.replace(field.config, sh_degree=2))
    render(copy)
    assert len(calls) == 5, "a field config of other harmonics must encode again"
    for out in (again, again_written, changed, other):
        for key in ("rgb", "alpha", "depth"):
            assert torch.equal(out[key], first[key]), key

    ground = GroundPlane(extent=0.9, shadow_resolution=16)
    shadowed = render(copy, ground=ground)
    assert len(calls) == 6 and calls[5] is not copy, "only the shadow map's rays are encoded"
    render(copy, ground=ground)
    assert len(calls) == 7 and calls[6] is not copy, "the shadow map's rays must not evict the camera's encoding"
    assert torch.equal(render(copy, ground=ground)["rgb"], shadowed["rgb"])


def test_a_directions_key_names_the_rays_whose_encoding_is_reused(teapot, monkeypatch):
    """With a key the caller names the directions: the same key reuses the encoding without looking at the values,
    another key (or none after a key) encodes them again."""
    model, field, renderer, q = teapot
    renderer = DeformedRenderer(field, renderer.grid, model)
    calls = []
    encode = field.encode_directions
    monkeypatch.setattr(field, "encode_directions", lambda d: calls.append(d) or encode(d))
    cameras = _look_at((-1.2, 1.6, -1.0), (0.0, 0.1, 0.1), (0.0, 1.0, 0.0), 16, fov=0.9)
    origins, directions = (t.to(backend.torch_device()).contiguous() for t in cameras.rays(0))
    frame = renderer.frame(q)

    def render(rays_directions, key):
        return renderer.render(q, rays=(origins, rays_directions), frame=frame, directions_key=key)

    first = render(directions, ("view", 0))
    same = render(directions.clone(), ("view", 0))
    assert len(calls) == 1, "the same key must reuse the encoding"
    assert torch.equal(same["rgb"], first["rgb"])
    render(directions, ("view", 1))
    assert len(calls) == 2, "another key must encode again"
    render(directions, None)
    assert len(calls) == 3, "no key after a key must encode again"


def _random_teapot_field(seed: int):
    """A randomly initialised NGP field over the teapot's box and its fully occupied grid (every sample queried)."""
    lo, hi = scene_mesh("teapot").bounds
    aabb = torch.stack([lo - 0.05, hi + 0.05])
    torch.manual_seed(seed)
    field = NGPField(NGPConfig(), aabb).to(backend.torch_device())
    return field, OccupancyGrid.for_field(field)


def test_float16_copies_follow_the_fields_weights(teapot):
    """Under half precision the renderer queries float16 copies of the field's MLPs; weights loaded into the field
    afterwards are copied again, so the next image is that of a renderer built after the change."""
    model, _, _, q = teapot
    if backend.torch_device().type != "cuda":
        pytest.skip("the float16 copies of the MLPs are made on CUDA only")
    field, grid = _random_teapot_field(seed=0)
    cameras = _look_at((-1.2, 1.6, -1.0), (0.0, 0.1, 0.1), (0.0, 1.0, 0.0), 16, fov=0.9)
    renderer = DeformedRenderer(field, grid, model, half_precision=True)
    with torch.no_grad():
        before = renderer.render(q, cameras)["rgb"]
        weights = {name: value.clone() for name, value in field.state_dict().items()}
        weights["encoding.table"].fill_(1.0)  # an opaque body: every feature 1, ...
        weights["density_mlp.2.weight"].fill_(1.0)  # ... every hidden unit adding to the density
        field.load_state_dict(weights)
        after = renderer.render(q, cameras)["rgb"]
        fresh = DeformedRenderer(field, grid, model, half_precision=True).render(q, cameras)["rgb"]
    assert float((after - before).abs().max()) > 1e-2, "the new weights must change the image"
    torch.testing.assert_close(after, fresh, rtol=0, atol=1e-3)  # float16 products in either renderer


def _light_cosine(ground: GroundPlane) -> float:
    light = torch.nn.functional.normalize(torch.tensor(ground.light_direction), dim=0)
    return float(light[1])


def test_bad_arguments_raise_clear_errors(teapot):
    model, field, renderer, q = teapot
    cameras = scene_cameras("teapot", views=1, resolution=8)
    with pytest.raises(ValueError, match="unknown mode 'cubic'"):
        renderer.render(q, cameras, mode="cubic")
    with pytest.raises(ValueError, match=r"q must be the model's DOFs"):
        renderer.render(q[:-1], cameras)
    with pytest.raises(ValueError, match="either cameras"):
        renderer.render(q, cameras, rays=cameras.rays(0))
    with pytest.raises(ValueError, match="pointing up"):
        GroundPlane(light_direction=(0.0, -1.0, 0.0))
    with pytest.raises(ValueError, match="cutoff_scale must be positive"):
        DeformedRenderer(field, renderer.grid, model, cutoff_scale=0.0)


def test_bucketed_sample_counts_are_few_and_close():
    """The sample count a round queries is padded to one of 8 sizes an octave: never below the count, at most an
    eighth (or 128) above it, so the field's products see few shapes."""
    counts = list(range(1, 5000)) + [10**5 + 7, 2**20 - 1, 2**20, 3 * 10**6 + 11]
    for count in counts:
        padded = bucket_size(count)
        assert count <= padded <= max(count + 127, count * 9 // 8 + 1), (count, padded)
    assert len({bucket_size(c) for c in range(2**16, 2**17)}) <= 9
