import numpy as np
import pytest
import torch
from PIL import Image

from pienerf.nerf.training_curve import (
    ERROR_FULL_SCALE,
    CurvePoint,
    TrainingCurve,
    error_heat_map,
    train_curve,
    write_error_images,
)


def _curve(*psnrs: float) -> TrainingCurve:
    points = [CurvePoint(5.0 * (k + 1), 100 * (k + 1), p, 0.9, (p,)) for k, p in enumerate(psnrs)]
    return TrainingCurve(points, torch.zeros(0))


def test_seconds_to_a_psnr_interpolate_between_checkpoints():
    assert _curve(20.0, 28.0, 32.0).seconds_to_psnr(30.0) == pytest.approx(12.5)  # halfway from 10 s to 15 s
    assert _curve(31.0, 33.0).seconds_to_psnr(30.0) == 5.0  # the first checkpoint already reaches it
    assert _curve(20.0, 25.0).seconds_to_psnr(30.0) is None
    assert _curve(20.0, 25.0).points[1].record() == {"seconds": 10.0, "steps": 200, "psnr": 25.0, "ssim": 0.9}


def test_checkpoint_times_must_rise():
    with pytest.raises(ValueError, match="positive training times in increasing order"):
        train_curve(None, None, [1.0, 1.0])
    with pytest.raises(ValueError, match="positive training times in increasing order"):
        train_curve(None, None, [])


def test_heat_map_spans_the_colour_map_from_no_error_to_full_scale():
    target = torch.full((4, 5, 3), 0.5)
    render = target.clone()
    render[0] += 2 * ERROR_FULL_SCALE  # saturates
    render[1] += 0.5 * ERROR_FULL_SCALE
    heat = error_heat_map(render, target)
    assert heat.shape == (4, 5, 3) and heat.dtype == np.uint8
    assert (heat[2:] == heat[2, 0]).all() and heat[2, 0].sum() < 30  # inferno starts near black
    assert heat[0, 0].sum() > 3 * 200  # and ends near white-yellow
    assert heat[2, 0].sum() < heat[1, 0].sum() < heat[0, 0].sum()
    with pytest.raises(ValueError, match=r"two \[H, W, 3\] images of one shape"):
        error_heat_map(render, target[:2])


def test_error_images_hold_render_truth_and_heat_map_side_by_side(tmp_path):
    generator = torch.Generator().manual_seed(0)
    targets = torch.rand(2, 40, 48, 3, generator=generator)
    renders = (targets + 0.05).clamp(0.0, 1.0)
    files = write_error_images(tmp_path / "images", ["./train/r_0", "./test/r_0"], renders, targets, [26.0, 21.5])
    assert set(files["views"]) == {"./train/r_0", "./test/r_0"}
    paths = [tmp_path / "images" / name for name in ("r_0.png", "r_0_2.png", "sheet.png")]
    assert sorted(map(str, paths[:2])) == sorted(files["views"].values()) and files["sheet"] == str(paths[2])
    for path in paths[:2]:
        with Image.open(path) as image:
            assert image.size == (3 * 48, 22 + 40) and image.mode == "RGB"
            pixels = np.asarray(image)
        truth = targets[0 if path.name == "r_0.png" else 1]
        expected = truth.mul(255.0).round().to(torch.uint8).numpy()
        assert np.array_equal(pixels[22:, 48:96], expected)  # the middle third is the ground truth
    with Image.open(paths[2]) as sheet:
        assert sheet.size == (3 * 48, 2 * (22 + 40))
    assert not [p for p in (tmp_path / "images").iterdir() if "partial" in p.name]
    with pytest.raises(ValueError, match="one name, render, target and PSNR per view"):
        write_error_images(tmp_path, ["a"], renders, targets, [1.0, 2.0])
