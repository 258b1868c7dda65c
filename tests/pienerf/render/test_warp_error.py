"""pienerf.render.warp_error: the region is the projected discs of the chosen material; on it, PSNR over white and the
silhouettes' intersection over union compare a render with its reference, and a region without material is refused."""

from __future__ import annotations

import math

import pytest
import torch

from kernels.image_metrics import psnr
from pienerf.nerf.cameras import look_at_cameras
from pienerf.render.warp_error import WarpErrorProbe, region_error, region_mask
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from tests.pienerf.bodies import lattice


def _cameras(width=64, height=48):
    return look_at_cameras([[0.0, 0.0, 2.0]], [[0.0, 0.0, 0.0]], width, height, 40.0)


def test_region_mask_is_the_projected_disc_widened_by_the_dilation():
    cameras = _cameras()
    focal = float(cameras.fx[0])
    point, radius = torch.zeros(1, 3), torch.tensor([0.1])
    disc = region_mask(point, radius, cameras, 0, dilation=0.0)
    reach = focal * 0.1 / 2.0
    assert disc.shape == (48, 64)
    assert int(disc.sum()) == pytest.approx(math.pi * reach**2, rel=0.15)
    rows, cols = torch.nonzero(disc, as_tuple=True)
    assert float(cols.float().mean() + 0.5) == pytest.approx(32.0, abs=0.5)
    assert float(rows.float().mean() + 0.5) == pytest.approx(24.0, abs=0.5)
    wider = region_mask(point, radius, cameras, 0, dilation=3.0)
    assert (wider | disc).equal(wider) and int(wider.sum()) == pytest.approx(math.pi * (reach + 3) ** 2, rel=0.15)
    behind = region_mask(torch.tensor([[0.0, 0.0, 3.0]]), radius, cameras, 0)
    assert not behind.any(), "a point behind the camera covers nothing"
    with pytest.raises(ValueError, match="dilation must be"):
        region_mask(point, radius, cameras, 0, dilation=-1.0)


def test_region_error_compares_colours_over_white_and_silhouettes_on_the_region():
    reference = torch.zeros(4, 5, 4)
    reference[:2, :, :3] = torch.tensor([0.2, 0.4, 0.6])
    reference[:2, :, 3] = 1.0  # the top two rows: 10 pixels of silhouette
    rendered = reference.clone()
    assert region_error(reference, rendered, torch.ones(4, 5, dtype=torch.bool)).to_dict() == {
        "psnr_db": math.inf,
        "silhouette_iou": 1.0,
        "pixels": 10,
    }
    rendered[1, :, 3] = 0.4  # one row fades below the silhouette threshold: seen over white
    error = region_error(reference, rendered, torch.ones(4, 5, dtype=torch.bool))
    assert error.silhouette_iou == pytest.approx(0.5) and error.pixels == 10
    over_white = lambda image: image[..., :3] * image[..., 3:] + 1.0 - image[..., 3:]  # noqa: E731
    expected = psnr(over_white(rendered)[:2], over_white(reference)[:2])
    assert error.psnr_db == pytest.approx(float(expected))
    top_row = torch.zeros(4, 5, dtype=torch.bool)
    top_row[0] = True
    assert region_error(reference, rendered, top_row).silhouette_iou == 1.0, "only the region counts"
    empty = region_error(reference, rendered, torch.zeros(4, 5, dtype=torch.bool))
    assert empty.psnr_db is None and empty.silhouette_iou is None and empty.pixels == 0
    with pytest.raises(ValueError, match=r"\[H, W, 4\]"):
        region_error(reference, rendered[..., :3], top_row)


def test_probe_refuses_a_region_without_material():
    position, volume = lattice((0.3, 0.1, 0.1), 0.05)
    model = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=2, kernel_lloyd_iterations=0))
    mesh = (torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="no particle of the body rests in the region box"):
        WarpErrorProbe(model, mesh, None, None, {"nerf": "quadratic"}, ([1.0, 1.0, 1.0], [2.0, 2.0, 2.0]))
    with pytest.raises(ValueError, match="lo <= hi"):
        WarpErrorProbe(model, mesh, None, None, {"nerf": "quadratic"}, ([0.3, 0.0, 0.0], [0.0, 0.1, 0.1]))
