import math

import pytest
import torch
import trimesh

from kernels import backend
from pienerf.sim.density import Box, Capsule, MeshDensity, Sphere, Union

ROTATION = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.3, 0.2], [0.3, 0.0, -0.5], [-0.2, 0.5, 0.0]]))


def _shapes():
    return {
        "sphere": Sphere([0.1, -0.2, 0.3], 0.5),
        "box": Box([0.0, 0.1, 0.0], [0.4, 0.2, 0.3], rotation=ROTATION),
        "capsule": Capsule([-0.3, 0.0, 0.0], [0.3, 0.2, 0.1], 0.15),
        "union": Union(Sphere([0.3, 0.0, 0.0], 0.3), Box([-0.2, 0.0, 0.0], [0.25, 0.2, 0.2])),
    }


def _boundary_points(field, n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """Points where the density is neither saturated nor vanishing, so its gradient is large."""
    generator = torch.Generator().manual_seed(seed)
    lo, hi = field.bounds
    x = (lo + (hi - lo) * torch.rand(400_000, 3, generator=generator, dtype=torch.float64)).to(dtype)
    x = x.to(backend.torch_device())
    ratio = field.density(x) / field.max_density
    x = x[(ratio > 0.02) & (ratio < 0.98)][:n]
    assert x.shape[0] == n, "too few boundary points for the test"
    return x


def _finite_difference_grad(field, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    columns = []
    for axis in range(3):
        step = torch.zeros(3, dtype=x.dtype, device=x.device)
        step[axis] = h
        columns.append((field.density(x + step) - field.density(x - step)) / (2.0 * h))
    return torch.stack(columns, dim=-1)


@pytest.mark.parametrize("name", ["sphere", "box", "capsule", "union"])
def test_shape_gradients_match_finite_differences(device, name):
    field = _shapes()[name]
    x = _boundary_points(field, 200, seed=0)
    grad = field.density_grad(x)
    assert grad.shape == (200, 3) and grad.dtype == torch.float64
    assert float(grad.norm(dim=-1).min()) > 1.0, "points must sit where the density changes"
    torch.testing.assert_close(grad, _finite_difference_grad(field, x), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("name", ["sphere", "box", "capsule", "union"])
def test_density_is_sigmoid_of_signed_distance_in_float32(device, name):
    field = _shapes()[name]
    x = _boundary_points(field, 100, seed=1, dtype=torch.float32)
    sigma = field.density(x)
    assert sigma.dtype == torch.float32 and sigma.shape == (100,)
    expected = field.max_density * torch.sigmoid(-field.signed_distance(x.double()) / field.softness)
    torch.testing.assert_close(sigma.double(), expected, rtol=1e-4, atol=1e-4)
    assert field.density_grad(x).dtype == torch.float32
    lo, hi = field.bounds
    corners = torch.stack([lo, hi, torch.stack([lo[0], hi[1], lo[2]])]).to(device=x.device)
    assert float(field.density(corners).max()) < 1e-6 * field.max_density


def test_analytic_signed_distances(device):
    x = torch.tensor([[0.1, -0.2, 1.3], [0.1, -0.2, 0.3]], dtype=torch.float64, device=backend.torch_device())
    torch.testing.assert_close(
        _shapes()["sphere"].signed_distance(x), torch.tensor([0.5, -0.5], device=x.device, dtype=torch.float64)
    )
    box = Box([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])
    y = torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 3.0, 0.0]], dtype=torch.float64, device=x.device)
    torch.testing.assert_close(
        box.signed_distance(y), torch.tensor([1.0, -1.0, math.sqrt(2.0)], device=x.device, dtype=torch.float64)
    )
    capsule = Capsule([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.5)
    z = torch.tensor([[0.5, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64, device=x.device)
    torch.testing.assert_close(
        capsule.signed_distance(z), torch.tensor([0.5, 0.5], device=x.device, dtype=torch.float64)
    )


def test_union_is_the_densest_member(device):
    a, b = Sphere([0.3, 0.0, 0.0], 0.3), Box([-0.2, 0.0, 0.0], [0.25, 0.2, 0.2], softness=0.003)
    union = Union(a, b, softness=0.003)
    x = _boundary_points(union, 300, seed=2)
    a_same = Sphere([0.3, 0.0, 0.0], 0.3, softness=0.003)
    torch.testing.assert_close(union.density(x), torch.maximum(a_same.density(x), b.density(x)))


def test_level_distance_inverts_the_sigmoid(device):
    sphere = Sphere([0.0, 0.0, 0.0], 1.0)
    d = sphere.level_distance(1e-2)
    x = torch.tensor([[1.0 + d, 0.0, 0.0]], dtype=torch.float64, device=backend.torch_device())
    torch.testing.assert_close(sphere.density(x), torch.tensor([1e-2], dtype=torch.float64, device=x.device))
    assert d == pytest.approx(0.01 * math.log(50.0 / 1e-2 - 1.0))


def test_mesh_density_approaches_the_analytic_sphere(device):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    field = MeshDensity(mesh, resolution=40)
    sphere = Sphere([0.0, 0.0, 0.0], 1.0)
    assert field.softness == pytest.approx(sphere.softness, rel=1e-3)
    x = _boundary_points(sphere, 500, seed=3)
    # The facets lie up to ~4 mm inside the unit sphere; trilinear interpolation adds ~h²/8R ≈ 0.5 mm.
    error = (field.signed_distance(x) - sphere.signed_distance(x)).abs()
    assert float(error.max()) < 6e-3
    generator = torch.Generator().manual_seed(4)
    far = (torch.rand(2000, 3, generator=generator, dtype=torch.float64) * 2.8 - 1.4).to(x.device)
    inside = sphere.signed_distance(far) < -0.01
    outside = sphere.signed_distance(far) > 0.01
    mesh_distance = field.signed_distance(far)
    assert bool((mesh_distance[inside] < 0).all()) and bool((mesh_distance[outside] > 0).all())


@pytest.mark.parametrize("mesh", ["icosphere", "box"])
def test_mesh_gradient_matches_finite_differences(device, mesh):
    if mesh == "icosphere":
        field = MeshDensity(trimesh.creation.icosphere(subdivisions=2, radius=0.5), softness=0.03, resolution=24)
    else:
        field = MeshDensity(trimesh.creation.box(extents=[0.8, 0.5, 0.4]), softness=0.03, resolution=24)
    x = _boundary_points(field, 200, seed=5)
    # Trilinear interpolation is smooth inside a cell: keep points away from cell faces.
    u = (x.cpu() - field.grid_lo) / field.grid_spacing
    x = x[((u - u.floor() - 0.5).abs() < 0.4).all(dim=1).to(x.device)]
    assert x.shape[0] > 50
    torch.testing.assert_close(field.density_grad(x), _finite_difference_grad(field, x), rtol=1e-5, atol=1e-4)


def test_mesh_density_of_a_box_matches_the_analytic_box_near_its_faces(device):
    field = MeshDensity(trimesh.creation.box(extents=[0.8, 0.5, 0.4]), resolution=32)
    box = Box([0.0, 0.0, 0.0], [0.4, 0.25, 0.2])
    x = _boundary_points(box, 300, seed=6)
    error = (field.signed_distance(x) - box.signed_distance(x)).abs()
    # A box's distance is piecewise linear, so interpolation is exact except in cells that straddle
    # its kinks (along edges and the inner ridges), where it errs by a fraction of a cell.
    assert float(error.median()) < 1e-9
    assert float(error.max()) < 0.25 * float(field.grid_spacing.max())


def test_bad_input_is_refused_with_the_fix(device):
    open_mesh = trimesh.creation.icosphere(subdivisions=1)
    open_mesh = trimesh.Trimesh(open_mesh.vertices, open_mesh.faces[:-1])
    with pytest.raises(ValueError, match="watertight.*fill_holes"):
        MeshDensity(open_mesh)
    with pytest.raises(ValueError, match="radius must be positive"):
        Sphere([0.0, 0.0, 0.0], -1.0)
    with pytest.raises(ValueError, match="proper rotation"):
        Box([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], rotation=2.0 * torch.eye(3))
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        Sphere([0.0, 0.0, 0.0], 1.0).density(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="softness"):
        Sphere([0.0, 0.0, 0.0], 1.0, softness=0.0)
    with pytest.raises(TypeError, match="SDFDensity"):
        Union(Sphere([0.0, 0.0, 0.0], 1.0), "sphere")
