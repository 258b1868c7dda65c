import pytest
import torch

from kernels import backend
from kernels.reference import spatial_hash as reference
from kernels.spatial_hash import SpatialHash, knn, radius_neighbours


def _cloud(n: int, seed: int, scale: float = 1.0, shift: float = 0.0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=generator) * scale + shift).to(backend.torch_device())


def _as_sets(index: torch.Tensor, count: torch.Tensor) -> list[set[int]]:
    return [set(row[: int(c)].tolist()) for row, c in zip(index.cpu(), count.cpu(), strict=True)]


def test_radius_neighbours_match_brute_force(device):
    points, queries = _cloud(3000, 0), _cloud(500, 1, scale=1.2, shift=-0.1)
    index, count = radius_neighbours(points, queries, 0.1, 64)
    expected = reference.radius_neighbours(points.cpu(), queries.cpu(), 0.1)
    assert int(count.max()) <= 64, "the test must not truncate rows"
    assert count.cpu().tolist() == [len(e) for e in expected]
    assert _as_sets(index, count) == [set(e.tolist()) for e in expected]
    padding = torch.arange(64, device=index.device)[None, :] >= count[:, None].long()
    assert bool((index[padding] == -1).all())


def test_radius_neighbours_truncated_rows_keep_true_count(device):
    points, queries = _cloud(3000, 2), _cloud(100, 3)
    index, count = radius_neighbours(points, queries, 0.15, 4)
    expected = reference.radius_neighbours(points.cpu(), queries.cpu(), 0.15)
    assert count.cpu().tolist() == [len(e) for e in expected]
    assert int(count.max()) > 4
    for row, c, e in zip(index.cpu(), count.cpu(), expected, strict=True):
        stored = row[: min(int(c), 4)].tolist()
        assert len(set(stored)) == len(stored) and set(stored) <= set(e.tolist())
        assert (row[min(int(c), 4) :] == -1).all()


@pytest.mark.parametrize("k", [3, 8])  # k = 3 keeps its best in registers, any other k in the row
def test_knn_matches_brute_force_on_random_points(device, k):
    points, queries = _cloud(2000, 4), _cloud(400, 5, scale=1.4, shift=-0.2)
    index, distance = knn(points, queries, k, 0.5)
    expected_index, expected_distance = reference.knn(points.cpu(), queries.cpu(), k, 0.5)
    torch.testing.assert_close(distance.cpu(), expected_distance, rtol=1e-6, atol=1e-7)
    assert torch.equal(index.cpu().long(), expected_index)


def test_knn_breaks_ties_by_index(device):
    # A lattice of exactly representable points: many queries see several points at equal distances.
    axis = torch.arange(6, dtype=torch.float32) * 0.25
    points = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    points = points[torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(0))]
    cell_corners = points[(points < 1.2).all(dim=1)][:20]
    queries = torch.cat([cell_corners + 0.125, points[20:40]])
    device_points, device_queries = points.to(backend.torch_device()), queries.to(backend.torch_device())
    for k in (3, 10):
        index, distance = knn(device_points, device_queries, k, 1.0)
        expected_index, expected_distance = reference.knn(points, queries, k, 1.0)
        assert torch.equal(distance.cpu(), expected_distance)
        assert torch.equal(index.cpu().long(), expected_index)
    assert bool((distance[:20, 0] == distance[:20, 7]).all()), "cell-centre queries have 8 equidistant corners"


def test_far_queries_and_k_beyond_point_count(device):
    points = _cloud(5, 6)
    far = torch.full((3, 3), 50.0, device=points.device)
    index, count = radius_neighbours(points, far, 0.5, 4)
    assert int(count.sum()) == 0 and bool((index == -1).all())
    index, distance = knn(points, far, 3, 2.0)
    assert bool((index == -1).all()) and bool(torch.isinf(distance).all())

    near = _cloud(7, 7)
    index, distance = knn(points, near, 8, 10.0)
    expected_index, expected_distance = reference.knn(points.cpu(), near.cpu(), 8, 10.0)
    assert bool((index[:, 5:] == -1).all()) and bool(torch.isinf(distance[:, 5:]).all())
    assert torch.equal(index.cpu().long(), expected_index)
    torch.testing.assert_close(distance.cpu(), expected_distance)


def test_one_build_serves_many_queries(device):
    points = _cloud(1500, 8)
    grid = SpatialHash(points, 0.08)
    for seed in (9, 10):
        queries = _cloud(200, seed)
        index, count = grid.radius_neighbours(queries, 0.08, 64)
        expected = reference.radius_neighbours(points.cpu(), queries.cpu(), 0.08)
        assert _as_sets(index, count) == [set(e.tolist()) for e in expected]
        k_index, _ = grid.knn(queries, 5, 1.0)
        assert torch.equal(k_index.cpu().long(), reference.knn(points.cpu(), queries.cpu(), 5, 1.0)[0])


def test_bad_input_is_refused_with_the_fix(device):
    empty = torch.zeros(0, 3, device=backend.torch_device())
    queries = _cloud(4, 11)
    with pytest.raises(ValueError, match="empty"):
        radius_neighbours(empty, queries, 0.1, 4)
    with pytest.raises(ValueError, match="empty"):
        knn(empty, queries, 2, 1.0)
    with pytest.raises(TypeError, match="float32"):
        SpatialHash(queries.double(), 0.1)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        SpatialHash(queries[:, :2].contiguous(), 0.1)
    with pytest.raises(ValueError, match="cell_size"):
        SpatialHash(queries, 0.0)
    with pytest.raises(ValueError, match="k must be"):
        knn(queries, queries, 0, 1.0)
