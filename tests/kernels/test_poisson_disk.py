import pytest
import torch

from kernels import backend
from kernels.poisson_disk import poisson_disk_select
from kernels.reference.poisson_disk import poisson_disk_select as reference_select


def _candidates(n: int, seed: int):
    generator = torch.Generator().manual_seed(seed)
    points = torch.rand(n, 3, generator=generator)
    radius = 0.04 + 0.08 * torch.rand(n, generator=generator)
    priority = torch.randperm(n, generator=generator).to(torch.int32)
    device = backend.torch_device()
    return points.to(device), radius.to(device), priority.to(device)


def _conflicts(points: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
    d = torch.cdist(points, points, compute_mode="donot_use_mm_for_euclid_dist")
    return d < torch.maximum(radius[:, None], radius[None, :])


@pytest.mark.parametrize("seed", [0, 1])
def test_selection_equals_sequential_dart_throwing(device, seed):
    points, radius, priority = _candidates(4000, seed)
    accepted = poisson_disk_select(points, radius, priority)
    assert torch.equal(accepted.cpu(), reference_select(points, radius, priority).cpu())


def test_selection_is_a_maximal_poisson_disk_set(device):
    points, radius, priority = _candidates(2500, 2)
    accepted = poisson_disk_select(points, radius, priority).cpu()
    conflict = _conflicts(points.cpu(), radius.cpu())
    conflict.fill_diagonal_(False)
    assert not bool(conflict[accepted][:, accepted].any()), "two accepted candidates conflict"
    assert bool(conflict[~accepted][:, accepted].any(dim=1).all()), "a rejected candidate could be added"
    assert 0 < int(accepted.sum()) < accepted.numel()


def test_bad_input_is_refused(device):
    points, radius, priority = _candidates(10, 3)
    with pytest.raises(ValueError, match="distinct"):
        poisson_disk_select(points, radius, torch.zeros_like(priority))
    with pytest.raises(ValueError, match="positive"):
        poisson_disk_select(points, torch.zeros_like(radius), priority)
    with pytest.raises(ValueError, match="int32"):
        poisson_disk_select(points, radius, priority.long())
    assert poisson_disk_select(points[:0], radius[:0], priority[:0]).numel() == 0
