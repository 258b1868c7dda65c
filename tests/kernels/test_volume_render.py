import math

import pytest
import torch

from kernels import backend
from kernels.backend import FRAMEWORKS
from kernels.reference.volume_render import composite_torch, march_rays_torch
from kernels.volume_render import (
    DEFAULT_TRANSMITTANCE_THRESHOLD,
    composite,
    composite_accumulate,
    composite_backward,
    composite_forward,
    composite_start,
    gather_ray_rows,
    march_rays,
    march_resume,
    march_start,
)

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _packed(counts: list[int], seed: int = 0, sigma_scale: float = 20.0):
    """Random packed samples for rays with the given sample counts (zeros give empty rays)."""
    generator = torch.Generator().manual_seed(seed)
    samples = sum(counts)
    device = backend.torch_device()
    offsets = torch.tensor([0, *torch.tensor(counts).cumsum(0).tolist()], dtype=torch.int32)
    deltas = torch.rand(samples, generator=generator) * 0.05 + 0.01
    sigmas = torch.rand(samples, generator=generator) * sigma_scale
    colors = torch.rand(samples, 3, generator=generator)
    depths = torch.cat([torch.cumsum(deltas[a:b], 0) + 1.0 for a, b in zip(offsets[:-1], offsets[1:], strict=True)])
    return tuple(t.to(device) for t in (sigmas, colors, deltas, depths, offsets))


def _rays(count: int, seed: int = 0):
    """Rays from a ring of cameras around the box, aimed near its centre."""
    generator = torch.Generator().manual_seed(seed)
    angle = torch.rand(count, generator=generator) * 2 * math.pi
    height = torch.rand(count, generator=generator) - 0.5
    origins = torch.stack([3 * torch.cos(angle), 3 * torch.sin(angle), height], -1)
    target = (torch.rand(count, 3, generator=generator) - 0.5) * 1.5
    directions = torch.nn.functional.normalize(target - origins, dim=-1)
    jitter = torch.rand(count, generator=generator)
    device = backend.torch_device()
    return origins.to(device), directions.to(device), jitter.to(device)


def _grid(resolution: int, fill: float, seed: int = 3) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(resolution, resolution, resolution, generator=generator) < fill).to(backend.torch_device())


def test_composite_forward_matches_reference_with_empty_rays(device):
    sigmas, colors, deltas, depths, offsets = _packed([5, 0, 17, 1, 0, 40, 3], sigma_scale=5.0)
    color, opacity, depth, used, weights = composite_forward(
        sigmas, colors, deltas, depths, offsets, return_weights=True
    )
    expected = composite_torch(sigmas, colors, deltas, depths, offsets)
    for value, reference in zip((color, opacity, depth, weights), expected, strict=True):
        torch.testing.assert_close(value, reference, rtol=1e-5, atol=1e-6)
    assert color[1].abs().sum() == 0 and opacity[4] == 0 and depth[1] == 0, "empty rays composite to nothing"
    assert used.tolist() == [5, 0, 17, 1, 0, 40, 3], "no ray reached the termination threshold"
    assert bool((opacity <= 1.0).all() and (opacity >= 0.0).all())


def test_early_termination_stops_where_transmittance_drops_below_threshold(device):
    sigmas, colors, deltas, depths, offsets = _packed([60, 60, 4], sigma_scale=400.0, seed=1)
    color, opacity, depth, used, weights = composite_forward(
        sigmas, colors, deltas, depths, offsets, return_weights=True
    )
    tau = (sigmas * deltas).double().cpu()
    for ray in range(2):
        a = int(offsets[ray])
        transmittance = torch.exp(-torch.cumsum(torch.cat([tau.new_zeros(1), tau[a : a + 60]]), 0))[:-1]
        expected_used = int((transmittance >= DEFAULT_TRANSMITTANCE_THRESHOLD).sum())
        assert int(used[ray]) == expected_used < 60, "dense rays must stop before their last sample"
        assert bool((weights[a + expected_used : a + 60] == 0).all()), "samples after termination carry no weight"
        # Compositing only the samples before termination gives the same pixel.
        head = slice(a, a + expected_used)
        truncated = composite_forward(
            sigmas[head],
            colors[head],
            deltas[head],
            depths[head],
            torch.tensor([0, expected_used], dtype=torch.int32, device=sigmas.device),
        )
        torch.testing.assert_close(truncated[0][0], color[ray], rtol=0, atol=0)
    assert opacity[0] > 1 - DEFAULT_TRANSMITTANCE_THRESHOLD
    expected = composite_torch(sigmas, colors, deltas, depths, offsets)
    for value, reference in zip((color, opacity, depth, weights), expected, strict=True):
        torch.testing.assert_close(value, reference, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("sigma_scale", [5.0, 400.0], ids=["translucent", "terminating"])
def test_backward_matches_reference_autograd(device, sigma_scale):
    sigmas, colors, deltas, depths, offsets = _packed([8, 0, 33, 1, 50, 12], sigma_scale=sigma_scale, seed=2)
    generator = torch.Generator().manual_seed(5)
    rays = offsets.shape[0] - 1
    g_color, g_opacity, g_depth = (
        torch.randn(*shape, generator=generator).to(sigmas.device) for shape in ((rays, 3), (rays,), (rays,))
    )

    s, c = sigmas.clone().requires_grad_(), colors.clone().requires_grad_()
    out = composite(s, c, deltas, depths, offsets)
    loss = (out["color"] * g_color).sum() + (out["opacity"] * g_opacity).sum() + (out["depth"] * g_depth).sum()
    grad_sigmas, grad_colors = torch.autograd.grad(loss, (s, c))

    s_ref, c_ref = sigmas.double().requires_grad_(), colors.double().requires_grad_()
    color, opacity, depth, _ = composite_torch(s_ref, c_ref, deltas, depths, offsets)
    loss_ref = (color * g_color).sum() + (opacity * g_opacity).sum() + (depth * g_depth).sum()
    grad_sigmas_ref, grad_colors_ref = torch.autograd.grad(loss_ref, (s_ref, c_ref))

    torch.testing.assert_close(grad_sigmas, grad_sigmas_ref.float(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(grad_colors, grad_colors_ref.float(), rtol=1e-4, atol=1e-6)
    assert grad_sigmas.abs().sum() > 0


def test_backward_is_zero_for_samples_after_termination(device):
    sigmas, colors, deltas, depths, offsets = _packed([50], sigma_scale=1000.0, seed=4)
    color, opacity, depth, used, _ = composite_forward(sigmas, colors, deltas, depths, offsets)
    ones = torch.ones_like(color), torch.ones_like(opacity), torch.ones_like(depth)
    grad_sigmas, grad_colors = composite_backward(
        *ones, sigmas, colors, deltas, depths, offsets, color, opacity, depth, used
    )
    n = int(used[0])
    assert n < 50
    assert bool((grad_sigmas[n:] == 0).all() and (grad_colors[n:] == 0).all())
    assert bool((grad_colors[:n] > 0).all())


def test_all_rays_empty(device):
    device_ = backend.torch_device()
    offsets = torch.zeros(4, dtype=torch.int32, device=device_)
    empty = torch.zeros(0, device=device_)
    sigmas = empty.clone().requires_grad_()
    colors = torch.zeros(0, 3, device=device_, requires_grad=True)
    out = composite(sigmas, colors, empty, empty, offsets, return_weights=True)
    assert out["color"].shape == (3, 3) and bool((out["color"] == 0).all()) and out["weights"].numel() == 0
    (out["color"].sum() + out["opacity"].sum()).backward()
    assert sigmas.grad.shape == (0,) and colors.grad.shape == (0, 3)


@pytest.mark.parametrize(
    ("min_step", "cone_angle", "max_step"), [(0.02, 0.0, None), (0.005, 0.01, 0.04)], ids=["constant", "cone"]
)
def test_march_matches_reference(device, min_step, cone_angle, max_step):
    origins, directions, jitter = _rays(1500)
    grid = _grid(16, 0.4)
    kwargs = dict(max_step=max_step, cone_angle=cone_angle, max_samples=48, jitter=jitter)
    samples = march_rays(origins, directions, 0.5, 6.0, grid, AABB, min_step, **kwargs)
    positions, depths, deltas, offsets = march_rays_torch(origins, directions, 0.5, 6.0, grid, AABB, min_step, **kwargs)
    assert torch.equal(samples.ray_offsets, offsets)
    torch.testing.assert_close(samples.positions, positions, rtol=0, atol=1e-5)
    torch.testing.assert_close(samples.depths, depths, rtol=0, atol=1e-5)
    torch.testing.assert_close(samples.deltas, deltas, rtol=0, atol=1e-6)
    assert int(samples.counts.max()) == 48, "some rays must reach max_samples"
    assert torch.equal(
        samples.ray_indices,
        torch.repeat_interleave(torch.arange(1500), samples.counts.long().cpu()).to(samples.ray_indices.device),
    )
    # Every emitted sample lies in an occupied cell.
    cells = ((samples.positions - AABB[0].to(positions)) / (2.0 / 16)).floor().long().clamp(0, 15)
    assert bool(grid[cells[:, 0], cells[:, 1], cells[:, 2]].all())


def test_march_through_full_grid_covers_the_box(device):
    origins, directions, _ = _rays(300, seed=7)
    step = 0.01
    samples = march_rays(origins, directions, 0.0, 100.0, _grid(8, 1.1), AABB, step, max_samples=4096)
    d = torch.where(directions.abs() < 1e-12, 1e-12, directions)
    t0, t1 = (AABB[0].to(d) - origins) / d, (AABB[1].to(d) - origins) / d
    enter, leave = torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)
    hits = enter < leave
    assert bool((samples.counts[~hits] == 0).all()), "rays missing the box get no samples"
    for ray in torch.nonzero(hits).flatten().tolist()[:50]:
        a, b = int(samples.ray_offsets[ray]), int(samples.ray_offsets[ray + 1])
        t = samples.depths[a:b]
        assert abs(float(t[0] - enter[ray])) < 1e-5, "the first sample sits on the box entry"
        assert float(t[-1]) < float(leave[ray]) <= float(t[-1]) + step + 1e-5, "the last step reaches the exit"
        torch.testing.assert_close(t.diff(), torch.full_like(t[1:], step), rtol=0, atol=2e-5)


def test_march_skips_empty_space(device):
    origins, directions, jitter = _rays(500, seed=8)
    empty = march_rays(origins, directions, 0.0, 10.0, _grid(16, -1.0), AABB, 0.01, jitter=jitter)
    assert empty.positions.shape == (0, 3) and empty.ray_offsets.shape == (501,)
    # One occupied cell in the middle: samples only there, on the same lattice as with a full grid.
    centre = torch.zeros(4, 4, 4, dtype=torch.bool, device=backend.torch_device())
    centre[1:3, 1:3, 1:3] = True
    sparse = march_rays(origins, directions, 0.0, 10.0, centre, AABB, 0.01, jitter=jitter)
    full = march_rays(origins, directions, 0.0, 10.0, _grid(4, 1.1), AABB, 0.01, jitter=jitter)
    assert 0 < sparse.positions.shape[0] < full.positions.shape[0]
    assert bool((sparse.positions.abs() <= 0.5 + 1e-5).all())
    inside = (full.positions.abs() < 0.5).all(-1)
    torch.testing.assert_close(sparse.depths, full.depths[inside], rtol=0, atol=1e-5)


def _march_in_rounds(origins, directions, near, far, grid, min_step, schedule, **kwargs):
    """Samples of every ray from rounds of ``march_resume`` (``schedule``: samples per ray of each round; the rays
    of a round are those whose previous round filled all its slots), gathered per ray in order."""
    state = march_start(origins, directions, near, far, AABB)
    rays = torch.arange(origins.shape[0], device=origins.device)
    per_ray = [[] for _ in range(origins.shape[0])]
    rounds = 0
    while rays.numel() > 0:
        k = schedule[min(rounds, len(schedule) - 1)]
        batch = march_resume(state, origins, directions, rays, grid, AABB, min_step, samples_per_ray=k, **kwargs)
        for i, ray in enumerate(rays.tolist()):
            n = int(batch.counts[i])
            per_ray[ray].append((batch.positions[i, :n], batch.depths[i, :n], batch.deltas[i, :n]))
        rays = rays[batch.counts == k]
        rounds += 1
    gathered = [[torch.cat(parts) for parts in zip(*chunks, strict=True)] for chunks in per_ray]
    return gathered, state, rounds


@pytest.mark.parametrize("framework", FRAMEWORKS)
@pytest.mark.parametrize(
    ("min_step", "cone_angle", "max_step"), [(0.02, 0.0, None), (0.005, 0.01, 0.04)], ids=["constant", "cone"]
)
def test_march_in_rounds_emits_exactly_the_full_march(device, min_step, cone_angle, max_step, framework):
    """Resuming each ray where its last round stopped reproduces the single march bit for bit (same lattice, same
    cone steps, same max_samples cap), whatever the samples per round, in either framework.

    The Taichi rounds equal :func:`march_rays` itself (the same loop). On the CPU so do Warp's; on CUDA the two
    compilers may fuse the march's multiply-adds differently, so there Warp's rounds are held to Warp's own full
    march, one round of ``max_samples`` slots."""
    origins, directions, _ = _rays(400, seed=11)
    grid = _grid(16, 0.4)
    kwargs = dict(max_step=max_step, cone_angle=cone_angle, max_samples=48)
    full = march_rays(origins, directions, 0.5, 6.0, grid, AABB, min_step, **kwargs)
    assert int(full.counts.max()) == 48, "some rays must reach max_samples"
    if framework == "warp" and device == "cuda":
        per_ray, state, _ = _march_in_rounds(
            origins, directions, 0.5, 6.0, grid.to(torch.uint8), min_step, [48], framework=framework, **kwargs
        )
        offsets = torch.zeros(origins.shape[0] + 1, dtype=torch.int32, device=origins.device)
        offsets[1:] = torch.cumsum(state.count, 0)
        positions, depths, deltas = (torch.cat([parts[i] for parts in per_ray]) for i in range(3))
        full = full._replace(positions=positions, depths=depths, deltas=deltas, ray_offsets=offsets)
    for schedule in ([1, 2, 4, 8], [5], [64]):
        per_ray, state, rounds = _march_in_rounds(
            origins, directions, 0.5, 6.0, grid.to(torch.uint8), min_step, schedule, framework=framework, **kwargs
        )
        assert rounds > 1 or schedule == [64]
        assert torch.equal(state.count, full.counts), "every ray emits as many samples as the full march"
        for ray in range(origins.shape[0]):
            a, b = int(full.ray_offsets[ray]), int(full.ray_offsets[ray + 1])
            positions, depths, deltas = per_ray[ray]
            assert torch.equal(positions, full.positions[a:b]), f"ray {ray}, schedule {schedule}"
            assert torch.equal(depths, full.depths[a:b]) and torch.equal(deltas, full.deltas[a:b])


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_march_resume_skips_rays_below_the_transmittance_threshold(device, framework):
    origins, directions, _ = _rays(64, seed=12)
    grid = _grid(8, 1.1)  # every cell occupied: every ray that meets the box emits samples
    state = march_start(origins, directions, 0.0, 10.0, AABB)
    transmittance = torch.ones(64, device=origins.device)
    transmittance[::2] = 1e-5
    rays = torch.arange(64, device=origins.device)
    batch = march_resume(
        state,
        origins,
        directions,
        rays,
        grid,
        AABB,
        0.01,
        samples_per_ray=4,
        transmittance=transmittance,
        transmittance_threshold=1e-4,
        framework=framework,
    )
    assert bool((batch.counts[::2] == 0).all()) and bool((state.count[::2] == 0).all()), "terminated rays stay put"
    assert bool((batch.counts[1::2] == 4).all()) and bool((state.count[1::2] == 4).all())


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_composite_in_rounds_equals_composite_forward(device, framework):
    """Compositing each ray's samples over several rounds gives the sums of one pass, early termination included:
    bit for bit in Taichi (the very loop of :func:`composite_forward`); in Warp, whose ``exp`` may differ from
    Taichi's in the last bit, to float rounding."""
    counts = [5, 0, 17, 1, 60, 60, 40, 3]
    sigmas, colors, deltas, depths, offsets = _packed(counts, seed=6, sigma_scale=300.0)
    color, opacity, depth, used, _ = composite_forward(sigmas, colors, deltas, depths, offsets)
    assert bool((used < torch.tensor(counts, device=used.device, dtype=used.dtype)).any()), "some rays must stop"
    state = composite_start(len(counts), sigmas.device)
    done = [0] * len(counts)
    schedule = (1, 2, 3, 7, 64)
    for round_, k in enumerate(schedule):
        rays, parts = [], []
        for ray, n in enumerate(counts):
            take = min(k, n - done[ray])
            # Rays sit out some rounds (as a renderer's rays drop out); the last round takes what is left.
            if take > 0 and ((ray + round_) % 2 == 0 or round_ == len(schedule) - 1):
                start = int(offsets[ray]) + done[ray]
                rays.append(ray)
                parts.append(torch.arange(start, start + take))
                done[ray] += take
        index = torch.cat(parts).to(sigmas.device)
        round_offsets = torch.tensor([0, *torch.tensor([len(p) for p in parts]).cumsum(0).tolist()], dtype=torch.int32)
        composite_accumulate(
            state,
            torch.tensor(rays, device=sigmas.device),
            sigmas[index],
            colors[index],
            deltas[index],
            depths[index],
            round_offsets.to(sigmas.device),
            framework=framework,
        )
    assert done == counts
    if framework == "taichi":
        assert torch.equal(state.color, color) and torch.equal(state.opacity, opacity)
        assert torch.equal(state.depth, depth)
    for value, expected_value in zip(state[:3], (color, opacity, depth), strict=True):
        torch.testing.assert_close(value, expected_value, rtol=1e-6, atol=1e-7)
    expected = composite_torch(sigmas, colors, deltas, depths, offsets)
    torch.testing.assert_close(state.color, expected[0], rtol=1e-5, atol=1e-6)


def test_bad_inputs_raise_clear_errors(device):
    sigmas, colors, deltas, depths, offsets = _packed([3, 2])
    with pytest.raises(TypeError, match="float32"):
        composite_forward(sigmas.double(), colors, deltas, depths, offsets)
    with pytest.raises(ValueError, match=r"colors must be \[5, 3\]"):
        composite_forward(sigmas, colors[:4], deltas, depths, offsets)
    with pytest.raises(TypeError, match="int32"):
        composite_forward(sigmas, colors, deltas, depths, offsets.long())
    if offsets.device.type == "cpu":
        with pytest.raises(ValueError, match="rise from 0 to S"):
            composite_forward(sigmas, colors, deltas, depths, offsets.flip(0).contiguous())
    origins, directions, _ = _rays(4)
    grid = _grid(4, 0.5)
    with pytest.raises(ValueError, match="aabb"):
        march_rays(origins, directions, 0.0, 1.0, grid, AABB.flip(0), 0.1)
    with pytest.raises(ValueError, match="occupancy"):
        march_rays(origins, directions, 0.0, 1.0, grid.float(), AABB, 0.1)
    with pytest.raises(ValueError, match="min_step"):
        march_rays(origins, directions, 0.0, 1.0, grid, AABB, 0.0)
    with pytest.raises(ValueError, match="near"):
        march_rays(origins, directions, torch.zeros(3), 1.0, grid, AABB, 0.1)
    state = march_start(origins, directions, 0.0, 1.0, AABB)
    rays = torch.arange(4, device=origins.device)
    with pytest.raises(ValueError, match="samples_per_ray"):
        march_resume(state, origins, directions, rays, grid, AABB, 0.1, samples_per_ray=0)
    with pytest.raises(TypeError, match="int64"):
        march_resume(state, origins, directions, rays.int(), grid, AABB, 0.1, samples_per_ray=2)
    with pytest.raises(ValueError, match="march_start"):
        march_resume(state, origins[:3], directions[:3], rays[:3], grid, AABB, 0.1, samples_per_ray=2)
    sums = composite_start(2, sigmas.device)
    with pytest.raises(ValueError, match="one per CSR row"):
        composite_accumulate(sums, torch.arange(3, device=sigmas.device), sigmas, colors, deltas, depths, offsets)


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32])
def test_gather_ray_rows_kernel_matches_indexing(device, dtype):
    """Each slot's row of a per-ray table: the word-copy kernel gives what indexing gives, bit for bit."""
    generator = torch.Generator().manual_seed(21)
    dev = backend.torch_device()
    table = torch.randn(50, 16, generator=generator).to(device=dev, dtype=dtype)
    rays = torch.randperm(50, generator=generator)[:30].to(dev)
    k = 7
    slots = torch.sort(torch.randperm(30 * k, generator=generator)[:120]).values.to(dev)
    expected = table[rays[slots // k]]
    assert torch.equal(gather_ray_rows(table, rays, slots, k, kernel=True), expected)
    assert torch.equal(gather_ray_rows(table, rays, slots, k, kernel=False), expected)
    odd = table[:, :3].contiguous().half()  # 6-byte rows: indexing, unless the kernel is asked for
    torch.testing.assert_close(gather_ray_rows(odd, rays, slots, k), odd[rays[slots // k]])
    with pytest.raises(ValueError, match="whole 4-byte rows"):
        gather_ray_rows(odd, rays, slots, k, kernel=True)
