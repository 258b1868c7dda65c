"""Appearance estimation (PhysAvatar §3.3, Eq. 8): albedo and light from the capture on known geometry, relighting."""

import functools

import pytest
import torch

from kernels.image_metrics import psnr
from physavatar.capture import CameraRig, Lighting, dressed_scene, garment_albedo, render_capture, shade_mesh
from physavatar.fit.appearance import (
    GarmentPixels,
    albedo_error,
    albedo_loss,
    estimate_appearance,
    gather_garment_pixels,
    relight,
    render_pixels,
)
from physavatar.shapes import grid_sheet, icosphere

FRAMES = 3
TRUE_LIGHT = Lighting((0.45, 0.45, 0.5), (0.6, 0.55, 0.5), (0.3, 1.0, 0.2))
TRUE_TOTAL = (1.05, 1.0, 1.0)  # L_a + L_s of TRUE_LIGHT: the gauge to report the estimate in


@functools.lru_cache(maxsize=1)
def _scene(device: str):
    """A wavy striped sheet under a ball that moves across it (the ball's shadow sweeps the stripes), 4 views."""
    v, faces = grid_sheet(9, 9, 0.1)
    sheet = torch.stack(
        [v[:, 0] - 0.4, -0.3 + 0.04 * torch.sin(6.0 * v[:, 0]) * torch.cos(5.0 * v[:, 1]), v[:, 1] - 0.4], 1
    )
    ball, ball_faces = icosphere(2, 0.2)
    garment = sheet[None].repeat(FRAMES, 1, 1)
    body = torch.stack([ball + torch.tensor([0.15 * t - 0.15, 0.0, 0.05 * t]) for t in range(FRAMES)])
    albedo = garment_albedo(sheet, faces)
    rig = CameraRig.ring(4, 1.3, 1.0, (0.0, -0.3, 0.0), 48, 40, 40.0)
    capture = render_capture(garment, faces, body, ball_faces, albedo, (0.7, 0.7, 0.7), rig, TRUE_LIGHT, 25.0)
    return garment, faces, body, ball_faces, albedo, capture


def _garment_pixels_of_faces(garment, faces, body, body_faces, rig, keep_face):
    """``[T, C, H, W]`` bool: pixels whose first hit is a garment face with ``keep_face`` true."""
    vertices, all_faces, count = dressed_scene(garment, faces, body, body_faces)
    keep = torch.cat([keep_face.cpu(), torch.zeros(len(all_faces) - count, dtype=torch.bool)])
    white = torch.ones(len(all_faces), 3)
    out = []
    for t in range(len(vertices)):
        views = [shade_mesh(vertices[t], all_faces, white, rig, c, TRUE_LIGHT, 0).face.cpu() for c in range(len(rig))]
        face = torch.stack(views)
        out.append((face >= 0) & keep[face.clamp_min(0)])
    return torch.stack(out)


def test_estimate_removes_baked_shadows_and_relights(device):
    garment, faces, body, body_faces, albedo, capture = _scene(device)
    # The estimator traces occlusion with other directions (seed 5) than the capture did (seed 0): its transport
    # is a model of the images, not a copy of their renderer.
    estimate = estimate_appearance(
        garment, faces, capture, body_frames=body, body_faces=body_faces, light_total=TRUE_TOTAL, seed=5, erode_px=1
    )
    assert estimate.albedo.shape == (len(faces), 3) and estimate.pixel_count > 2000
    assert int(estimate.observed.sum()) >= len(faces) - 2
    history = estimate.loss_history
    assert all(b <= a * (1 + 1e-12) for a, b in zip(history, history[1:], strict=False))
    assert history[-1] < 0.1 * history[0]

    baked = albedo_error(estimate.initial_albedo, albedo, estimate.observed)
    recovered = albedo_error(estimate.albedo, albedo, estimate.observed)
    absolute = albedo_error(estimate.albedo, albedo, estimate.observed, align=False)
    print(f"albedo error: baked texture {baked:.4f}, estimate {recovered:.4f} (no rescaling {absolute:.4f})")
    assert baked > 0.05  # the ball's moving shadow and the folds are baked into mean_t c_t
    assert recovered < 0.25 * baked and recovered < 0.03
    assert absolute < 0.03  # the gauge L_a + L_s = light_total gives absolute albedo when the total is known
    for estimated, true in ((estimate.lighting.ambient, TRUE_LIGHT.ambient), (estimate.lighting.sun, TRUE_LIGHT.sun)):
        assert max(abs(a - b) for a, b in zip(estimated, true, strict=True)) < 0.05
    assert estimate.lighting.sun_direction == TRUE_LIGHT.sun_direction

    # Relight: the same lamps moved and recoloured. Ground truth renders the true albedo under the new light; the
    # baked texture (best per-channel scale) is the "w/o appearance" baseline of the paper's Table 2.
    new_light = Lighting((0.25, 0.3, 0.35), (0.9, 0.8, 0.6), (-0.6, 1.0, -0.3))
    truth = relight(garment, faces, albedo, capture.rig, new_light, body, body_faces)
    relit = relight(garment, faces, estimate.albedo, capture.rig, new_light, body, body_faces)
    scale = (albedo.cpu() * estimate.initial_albedo).sum(0) / estimate.initial_albedo.square().sum(0)
    baseline = relight(garment, faces, estimate.initial_albedo * scale, capture.rig, new_light, body, body_faces)
    assert relit.shape == truth.shape == (FRAMES, 4, 40, 48, 3)
    seen = _garment_pixels_of_faces(garment, faces, body, body_faces, capture.rig, estimate.observed)
    seen = seen[..., None].expand_as(truth)
    ours, theirs = float(psnr(relit[seen], truth[seen])), float(psnr(baseline[seen], truth[seen]))
    print(f"relighting PSNR on garment pixels: estimate {ours:.1f} dB, baked texture {theirs:.1f} dB")
    assert ours > 32.0 and ours > theirs + 10.0


def test_transport_reproduces_the_captured_pixels(device):
    garment, faces, body, body_faces, albedo, capture = _scene(device)
    pixels = gather_garment_pixels(
        garment, faces, capture, body, body_faces, TRUE_LIGHT.sun_direction, seed=0, erode_px=0
    )
    assert len(pixels) == int(capture.masks.sum()) - int(
        (capture.images >= 1.0 - 0.5 / 255).any(-1)[capture.masks].sum()
    )
    assert bool((pixels.sun == 0).any()) and bool((pixels.ao < 1).any())  # shadows and occlusion were traced
    dev = pixels.rgb.device
    model = render_pixels(
        albedo.to(dev), torch.tensor(TRUE_LIGHT.ambient, device=dev), torch.tensor(TRUE_LIGHT.sun, device=dev), pixels
    )
    assert float((model - pixels.rgb).abs().max()) <= 0.5 / 255 + 1e-5  # the images, to 8-bit rounding
    eroded = gather_garment_pixels(garment, faces, capture, body, body_faces, None, erode_px=1)
    assert 0 < len(eroded) < len(pixels) and bool((eroded.sun == 0).all())


def test_ambient_only_model_of_the_paper(device):
    garment, faces, body, body_faces, albedo, _ = _scene(device)
    sky = Lighting((0.9, 0.85, 0.8), (0.0, 0.0, 0.0))
    rig = CameraRig.ring(3, 1.3, 1.0, (0.0, -0.3, 0.0), 48, 40, 40.0)
    capture = render_capture(garment, faces, body, body_faces, albedo, (0.7, 0.7, 0.7), rig, sky, 25.0)
    estimate = estimate_appearance(
        garment,
        faces,
        capture,
        body_frames=body,
        body_faces=body_faces,
        sun_direction=None,
        light_total=sky.ambient,
        erode_px=0,
    )
    assert estimate.lighting.sun == (0.0, 0.0, 0.0)
    assert max(abs(a - b) for a, b in zip(estimate.lighting.ambient, sky.ambient, strict=True)) < 1e-9
    baked = albedo_error(estimate.initial_albedo, albedo, estimate.observed)
    recovered = albedo_error(estimate.albedo, albedo, estimate.observed, align=False)
    assert recovered < 0.01 and recovered < 0.2 * baked


def test_adam_with_l1_loss_lowers_the_loss_and_the_error(device):
    garment, faces, body, body_faces, albedo, capture = _scene(device)
    estimate = estimate_appearance(
        garment,
        faces,
        capture,
        body_frames=body,
        body_faces=body_faces,
        method="adam",
        loss="l1",
        iterations=300,
        lr=0.02,
        seed=5,
        erode_px=1,
    )
    assert len(estimate.loss_history) == 301
    assert estimate.loss_history[-1] < 0.5 * estimate.loss_history[0]
    baked = albedo_error(estimate.initial_albedo, albedo, estimate.observed)
    assert albedo_error(estimate.albedo, albedo, estimate.observed) < 0.5 * baked


def test_render_pixels_gradients_match_the_analytic_ones():
    generator = torch.Generator().manual_seed(0)
    faces, count = 5, 40
    pixels = GarmentPixels(
        face=torch.randint(0, faces, (count,), generator=generator),
        ao=torch.rand(count, generator=generator),
        sun=torch.rand(count, generator=generator),
        rgb=torch.rand(count, 3, generator=generator),
        time=torch.zeros(count, dtype=torch.long),
        camera=torch.zeros(count, dtype=torch.long),
        face_count=faces,
        frame_count=1,
        sun_direction=(0.0, 1.0, 0.0),
    )
    albedo = torch.rand(faces, 3, dtype=torch.float64, generator=generator).requires_grad_(True)
    ambient = torch.tensor([0.4, 0.5, 0.6], dtype=torch.float64, requires_grad=True)
    sun = torch.tensor([0.7, 0.6, 0.5], dtype=torch.float64, requires_grad=True)
    albedo_loss(albedo, ambient, sun, pixels, "l2").backward()
    irradiance = pixels.ao.double()[:, None] * ambient.detach() + pixels.sun.double()[:, None] * sun.detach()
    residual = albedo.detach()[pixels.face] * irradiance - pixels.rgb.double()
    weight = 2.0 / residual.numel()
    expected_albedo = torch.zeros(faces, 3, dtype=torch.float64).index_add_(
        0, pixels.face, weight * residual * irradiance
    )
    torch.testing.assert_close(albedo.grad, expected_albedo)
    torch.testing.assert_close(
        ambient.grad, (weight * residual * albedo.detach()[pixels.face] * pixels.ao.double()[:, None]).sum(0)
    )
    torch.testing.assert_close(
        sun.grad, (weight * residual * albedo.detach()[pixels.face] * pixels.sun.double()[:, None]).sum(0)
    )


def test_bad_arguments_are_refused(device):
    garment, faces, body, body_faces, _, capture = _scene(device)
    with pytest.raises(ValueError, match="one mesh per captured frame"):
        estimate_appearance(garment[:2], faces, capture)
    with pytest.raises(ValueError, match="'l2' for ALS"):
        estimate_appearance(garment, faces, capture, loss="l1")
    with pytest.raises(ValueError, match=r"face_colors must be \[3, 128, 3\]"):
        estimate_appearance(garment, faces, capture, torch.zeros(3, 5, 3), body, body_faces)
