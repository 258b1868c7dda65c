import math

import pytest
import torch

from kernels import backend
from kernels import gaussian_splat as splat
from kernels.gaussian_splat import TILE_SIZE, bin_gaussians, gaussian_radii, rasterize_gaussians
from kernels.reference.gaussian_splat import rasterize_gaussians_torch

WIDTH, HEIGHT = 37, 29  # not square, not a multiple of the tile size
BACKGROUND = (0.2, 0.5, 0.8)


def _scene(views: int = 2, count: int = 60, seed: int = 0):
    """Random projected Gaussians: spread over (and past) the image, plus a dense opaque cluster.

    The first fifth of the Gaussians are near-opaque and crowd one spot, so pixels there stop early.
    The last three sit in front of ``near`` (culled), one before them has radius 0 (culled), and one has
    an indefinite conic (``power > 0`` along some directions).
    """
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(views, count, 2, generator=generator) * torch.tensor([WIDTH + 16.0, HEIGHT + 16.0]) - 8.0
    angle = torch.rand(views, count, generator=generator) * math.pi
    scale = torch.rand(views, count, 2, generator=generator) * 4.5 + 1.0
    cos, sin = torch.cos(angle), torch.sin(angle)
    rotation = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)
    covariance = rotation @ torch.diag_embed(scale**2) @ rotation.transpose(-1, -2)
    inverse = torch.linalg.inv(covariance)
    conics = torch.stack([inverse[..., 0, 0], inverse[..., 0, 1], inverse[..., 1, 1]], -1)
    opacities = torch.rand(views, count, generator=generator) * 0.9 + 0.05
    depths = torch.rand(views, count, generator=generator) * 4.0 + 0.5
    cluster = count // 5
    means[:, :cluster] = torch.tensor([WIDTH * 0.4, HEIGHT * 0.5]) + 1.5 * torch.randn(
        views, cluster, 2, generator=generator
    )
    opacities[:, :cluster] = torch.rand(views, cluster, generator=generator) * 0.03 + 0.97
    opacities[:, 0] = 0.999  # α clamped at 0.99 near its centre
    radii = gaussian_radii(conics)
    conics[:, cluster] = torch.tensor([0.05, 0.3, 0.05])  # indefinite: b² > ac
    radii[:, cluster] = 8
    depths[:, -3:] = torch.tensor([0.005, -1.0, 0.01])  # at or before near = 0.01
    radii[:, -4] = 0
    colors = torch.rand(views, count, 3, generator=generator)
    device = backend.torch_device()
    return tuple(t.to(device) for t in (means, conics, colors, opacities, depths, radii))


def _background() -> torch.Tensor:
    return torch.tensor(BACKGROUND, device=backend.torch_device())


def test_forward_matches_reference(device):
    means, conics, colors, opacities, depths, radii = _scene()
    background = _background()
    image, alpha = rasterize_gaussians(means, conics, colors, opacities, depths, radii, WIDTH, HEIGHT, background)
    assert image.shape == (2, HEIGHT, WIDTH, 3) and alpha.shape == (2, HEIGHT, WIDTH)
    inputs = [t.double() for t in (means, conics, colors, opacities)]
    image_ref, alpha_ref = rasterize_gaussians_torch(*inputs, depths, radii, WIDTH, HEIGHT, background.double())
    torch.testing.assert_close(image, image_ref.float(), rtol=0, atol=2e-5)
    torch.testing.assert_close(alpha, alpha_ref.float(), rtol=0, atol=2e-5)
    assert float(alpha.max()) > 0.999 and float(alpha.min()) < 0.01, "the scene has opaque and empty pixels"

    # Early termination triggers and matters: compositing every Gaussian gives other pixels.
    image_all, alpha_all = rasterize_gaussians_torch(
        *inputs, depths, radii, WIDTH, HEIGHT, background.double(), transmittance_min=0.0
    )
    assert float((image_all.float() - image).abs().max()) > 1e-3
    assert float(alpha.max()) <= 1.0 - 1e-4 + 1e-6 < float(alpha_all.max())

    # Culled Gaussians would show: moving the near ones behind the camera plane changes the image.
    uncull = depths.clone()
    uncull[:, -3:] = 0.2
    image_uncull, _ = rasterize_gaussians(means, conics, colors, opacities, uncull, radii, WIDTH, HEIGHT, background)
    assert float((image_uncull - image).abs().max()) > 1e-2

    # The order of the inputs does not matter (the rasterizer sorts by depth).
    perm = torch.randperm(means.shape[1], generator=torch.Generator().manual_seed(3)).to(means.device)
    shuffled = [t[:, perm].contiguous() for t in (means, conics, colors, opacities, depths, radii)]
    image_perm, alpha_perm = rasterize_gaussians(*shuffled, WIDTH, HEIGHT, background)
    torch.testing.assert_close(image_perm, image, rtol=0, atol=1e-6)
    torch.testing.assert_close(alpha_perm, alpha, rtol=0, atol=1e-6)


@pytest.mark.parametrize("per_tile", [True, False], ids=["per-tile", "per-pixel-atomic"])
def test_backward_matches_reference_autograd(device, per_tile, monkeypatch):
    if device == "cuda" and per_tile:
        pytest.skip("CUDA runs the per-pixel layout; the per-tile layout is the CPU's")
    monkeypatch.setattr(splat, "_backward_per_tile", lambda _device: per_tile)
    means, conics, colors, opacities, depths, radii = _scene(seed=1)
    generator = torch.Generator().manual_seed(5)
    weight_image = torch.randn(2, HEIGHT, WIDTH, 3, generator=generator).to(means.device)
    weight_alpha = torch.randn(2, HEIGHT, WIDTH, generator=generator).to(means.device)

    inputs = [t.clone().requires_grad_() for t in (means, conics, colors, opacities, _background())]
    image, alpha = rasterize_gaussians(*inputs[:4], depths, radii, WIDTH, HEIGHT, inputs[4])
    loss = (image * weight_image).sum() + (alpha * weight_alpha).sum()
    grads = torch.autograd.grad(loss, inputs)

    inputs_ref = [t.double().requires_grad_() for t in (means, conics, colors, opacities, _background())]
    image_ref, alpha_ref = rasterize_gaussians_torch(*inputs_ref[:4], depths, radii, WIDTH, HEIGHT, inputs_ref[4])
    loss_ref = (image_ref * weight_image.double()).sum() + (alpha_ref * weight_alpha.double()).sum()
    grads_ref = torch.autograd.grad(loss_ref, inputs_ref)

    names = ("means2d", "conics", "colors", "opacities", "background")
    for name, grad, grad_ref in zip(names, grads, grads_ref, strict=True):
        scale = float(grad_ref.abs().max())
        assert scale > 0, f"{name}: the scene must give a non-zero gradient"
        torch.testing.assert_close(
            grad, grad_ref.float(), rtol=1e-3, atol=1e-5 * scale, msg=lambda m, n=name: f"{n}: {m}"
        )
    culled = torch.zeros(means.shape[1], dtype=torch.bool)
    culled[-4:] = True
    for grad in grads[:4]:
        assert bool((grad[:, culled] == 0).all()), "culled Gaussians receive no gradient"


def test_expanded_colors_receive_the_sum_over_views(device):
    means, conics, colors, opacities, depths, radii = _scene(seed=2)
    base = colors[0].clone().requires_grad_()
    image, _ = rasterize_gaussians(means, conics, base.expand(2, -1, 3), opacities, depths, radii, WIDTH, HEIGHT)
    image.sum().backward()
    per_view = colors.clone().requires_grad_()
    image_views, _ = rasterize_gaussians(means, conics, per_view, opacities, depths, radii, WIDTH, HEIGHT)
    image_views.sum().backward()
    # A view's colour gradient is a sum over the pixels a Gaussian reaches of their blending weights (non-negative),
    # added atomically on CUDA in an order no run repeats: two runs differ by at most 2 n eps |sum|, n the pixels of a
    # view; the sum over the two views adds one rounding more.
    bound = (2 * WIDTH * HEIGHT + 1) * torch.finfo(torch.float32).eps
    torch.testing.assert_close(base.grad, per_view.grad.sum(0), rtol=bound, atol=0.0)


def test_empty_scene_gives_background_and_zero_gradients(device):
    means, conics, colors, opacities, depths, radii = _scene(views=3, count=12, seed=4)
    background = _background()
    far_away = means + 1000.0
    behind = torch.full_like(depths, -2.0)
    no_gaussians = [t[:, :0].contiguous() for t in (means, conics, colors, opacities, depths, radii)]
    for case in (
        (far_away, conics, colors, opacities, depths, radii),
        (means, conics, colors, opacities, behind, radii),
        (means, conics, colors, opacities, depths, torch.zeros_like(radii)),
        no_gaussians,
    ):
        inputs = [t.clone().requires_grad_() for t in case[:4]]
        image, alpha = rasterize_gaussians(*inputs, case[4], case[5], WIDTH, HEIGHT, background)
        assert torch.equal(image, background.expand(3, HEIGHT, WIDTH, 3))
        assert torch.equal(alpha, torch.zeros(3, HEIGHT, WIDTH, device=means.device))
        (image.sum() + alpha.sum()).backward()
        assert all(t.grad is not None and bool((t.grad == 0).all()) for t in inputs)
    image, alpha = rasterize_gaussians(*no_gaussians, WIDTH, HEIGHT)  # default background: black
    assert bool((image == 0).all())


def test_binning_lists_touched_tiles_front_to_back(device):
    means, conics, colors, opacities, depths, radii = _scene(seed=6)
    tiles = bin_gaussians(means, depths, radii, WIDTH, HEIGHT, near=0.01)
    tiles_x, tiles_y = tiles.tiles_x, tiles.tiles_y
    assert (tiles_x, tiles_y) == (3, 2)
    offsets, ids = tiles.tile_offsets.cpu().long(), tiles.gaussian_ids.cpu().long()
    means, depths, radii = means.cpu(), depths.cpu(), radii.cpu()
    views, count = depths.shape
    for view in range(views):
        for ty in range(tiles_y):
            for tx in range(tiles_x):
                tile = view * tiles_x * tiles_y + ty * tiles_x + tx
                listed = ids[offsets[tile] : offsets[tile + 1]]
                assert bool((listed // count == view).all())
                k = listed % count
                assert bool((depths[view, k].diff() >= 0).all()), "each list runs front to back"
                lo, hi = means[view] - radii[view, :, None], means[view] + radii[view, :, None]
                touches = (
                    (lo[:, 0] < (tx + 1) * TILE_SIZE)
                    & (hi[:, 0] >= tx * TILE_SIZE)
                    & (lo[:, 1] < (ty + 1) * TILE_SIZE)
                    & (hi[:, 1] >= ty * TILE_SIZE)
                    & (radii[view] > 0)
                    & (depths[view] > 0.01)
                )
                assert sorted(k.tolist()) == torch.nonzero(touches).flatten().tolist()


def test_gaussian_radii_are_three_sigma_of_the_major_axis():
    generator = torch.Generator().manual_seed(7)
    a = torch.rand(4, 50, 2, 2, generator=generator) * 3.0
    covariance = a @ a.transpose(-1, -2) + 0.1 * torch.eye(2)
    inverse = torch.linalg.inv(covariance)
    conics = torch.stack([inverse[..., 0, 0], inverse[..., 0, 1], inverse[..., 1, 1]], -1)
    radii = gaussian_radii(conics)
    expected = torch.ceil(3.0 * torch.linalg.eigvalsh(covariance.double())[..., -1].sqrt()).int()
    assert radii.dtype == torch.int32 and radii.shape == (4, 50)
    assert int((radii - expected).abs().max()) <= 1 and float((radii == expected).float().mean()) > 0.95
    not_definite = torch.tensor([[1.0, 2.0, 1.0], [-1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    assert gaussian_radii(not_definite).tolist() == [0, 0, 0]


def test_invalid_arguments_raise_value_errors_naming_them(device):
    means, conics, colors, opacities, depths, radii = _scene(count=8)
    args = dict(means2d=means, conics=conics, colors=colors, opacities=opacities, depths=depths, radii=radii)
    bad = {
        "means2d": means[..., :1].contiguous(),
        "conics": conics.double(),
        "colors": colors[:1].contiguous(),
        "opacities": opacities[..., None].contiguous(),
        "depths": depths[0].contiguous(),
        "radii": radii.float(),
    }
    for name, value in bad.items():
        with pytest.raises(ValueError, match=name):
            rasterize_gaussians(**{**args, name: value}, width=WIDTH, height=HEIGHT)
    with pytest.raises(ValueError, match="width"):
        rasterize_gaussians(**args, width=0, height=HEIGHT)
    with pytest.raises(ValueError, match="height"):
        rasterize_gaussians(**args, width=WIDTH, height=10.5)
    with pytest.raises(ValueError, match="background"):
        rasterize_gaussians(**args, width=WIDTH, height=HEIGHT, background=torch.zeros(4, device=means.device))
