"""The synthetic capture exported as a user's capture folder: read back, its defects as made, and prepared."""

import json

import numpy as np
import pytest
import torch

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.body import surface_closest_points
from physavatar.capture import load_capture_folder
from physavatar.pipeline import PipelineConfig, prepare
from tests.physavatar.pipeline.commands import run_avatar


@pytest.fixture(scope="module")
def exported(experiment, tmp_path_factory):
    out, _ = experiment
    folder = tmp_path_factory.mktemp("as-captured")
    result = run_avatar("export-capture", "--out", str(out), "--to", str(folder), "--push-depth-mm", "3")
    assert result.returncode == 0, result.stderr[-2000:]
    return out, folder


def test_the_exported_folder_reads_back_as_the_experiment_in_z_up(exported):
    out, folder = exported
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["up"] == "z" and "lighting" not in meta
    capture = load_capture_folder(folder)
    with np.load(out / "capture" / "inputs.npz") as data:
        body = torch.from_numpy(data["body_frames"])
        boundary = torch.from_numpy(data["boundary_index"])
    # OBJ coordinates carry 9 significant digits of metre-sized values, turned by an exact axis permutation
    torch.testing.assert_close(capture.body_frames, body, rtol=0.0, atol=1e-8)
    assert torch.equal(capture.boundary, boundary)
    assert capture.film.frame_count == body.shape[0] and capture.film.camera_count == 4


def test_the_pushed_vertices_start_three_millimetres_inside_the_body(exported, device):
    out, folder = exported
    record = json.loads((folder / "export.json").read_text())
    capture = load_capture_folder(folder)
    pushed = torch.tensor(record["pushed"])
    assert len(pushed) == round(0.05 * capture.garment_vertices.shape[0])
    x = capture.garment_vertices[pushed]
    _, distance, _, _ = surface_closest_points(capture.body_frames[0], capture.body_faces, x)
    # 3 mm along the normal of the nearest triangle: as deep where that triangle's interior was the nearest point,
    # shallower where an edge or a corner was (a neighbouring triangle may then be nearer), never deeper
    assert float(distance.max()) <= 3e-3 + 1e-8 and float(distance.median()) > 2.9e-3
    dev = backend.torch_device()
    inside = MeshBVH(capture.body_frames[0].to(dev), capture.body_faces.to(dev), winding_numbers=True).inside(x.to(dev))
    assert bool(inside.all())


def test_preparing_it_moves_the_pushed_vertices_out_past_the_barrier(exported, tmp_path, device):
    _, folder = exported
    config = PipelineConfig.smoke()
    prepare(config, tmp_path, capture=folder)
    record = json.loads((tmp_path / "prepare" / "prepare.json").read_text())
    pushed = len(json.loads((folder / "export.json").read_text())["pushed"])
    assert record["intersections"]["inside_body"] >= pushed
    assert record["intersections"]["remaining_inside"] == 0
    assert record["boundary"]["chosen"] == "given"
    with np.load(tmp_path / "prepare" / "inputs.npz") as data:
        x, body, faces = (torch.from_numpy(data[k]) for k in ("first_vertices", "body_frames", "body_faces"))
    _, distance, _, _ = surface_closest_points(body[0], faces, x)
    assert float(distance.min()) >= record["clearance_m"] - 1e-12
