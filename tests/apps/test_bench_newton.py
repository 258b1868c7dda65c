"""The peer workload cloth_step_newton: NVIDIA Newton's VBD cloth on cloth_step's skirt and walk."""

import math
import sys

import pytest
import torch
import warp as wp

from apps import bench
from apps.workloads import WorkloadUnavailable, load_all
from physavatar.body import Body, walk
from physavatar.drive import BodyDriver
from physavatar.garment import SHARED_GARMENTS, load_garment, place_on_body, select_boundary


def test_without_newton_the_workload_is_unavailable_and_names_the_fix(device, monkeypatch):
    monkeypatch.setitem(sys.modules, "newton", None)  # an import of newton now fails as if it were not installed
    with pytest.raises(WorkloadUnavailable, match=r"pip install -e '\.\[peers\]'"):
        load_all()["cloth_step_newton"].setup(device, "smoke")


@pytest.mark.data
@pytest.mark.slow
def test_newton_skirt_stays_on_the_waist_and_falls(device):
    pytest.importorskip("newton", reason="NVIDIA Newton is not installed (pip install -e '.[peers]')")
    if not (SHARED_GARMENTS / "skirt1252.obj").is_file():
        pytest.skip(f"the DiffCloth skirt skirt1252.obj is absent from {SHARED_GARMENTS}")

    case = load_all()["cloth_step_newton"].setup(device, "smoke")
    record = bench.measure("cloth_step_newton", case, device, "smoke", reps=2)  # a warm-up frame and two timed
    assert record["realtime_factor"] == pytest.approx(0.04 / record["median_s"]) and record["realtime_factor"] > 0
    assert math.isfinite(record["min_distance_body"]) and record["min_distance_body"] > 0
    assert math.isfinite(record["min_distance_self"]) and record["min_distance_self"] > 0
    assert record["vertices_inside_body"] >= 0 and record["frame"] == 3

    # the same scene, built as the workload builds it: the waist must sit on its driven targets of frame 3
    body = Body.mannequin(spacing=0.03)
    garment = place_on_body(load_garment(SHARED_GARMENTS / "skirt1252.obj"), body)
    boundary = select_boundary(garment, body, mode="waist")
    motion = walk(body.skeleton)
    driver = BodyDriver.from_motion(body, motion, garment.vertices, boundary, motion.num_frames - 1)
    x = wp.to_torch(case.run()).cpu().to(torch.float64)  # frame 4
    assert torch.isfinite(x).all()
    assert torch.allclose(x[boundary], driver.boundary_targets[4], atol=1e-5)
    free = torch.ones(x.shape[0], dtype=torch.bool)
    free[boundary] = False
    drop = garment.vertices[free, 1] - x[free, 1]
    assert drop.mean() > 0.01  # gravity pulled the hem down in 0.16 s ...
    assert (x - garment.vertices).norm(dim=1).max() < 0.3  # ... and nothing flew off
