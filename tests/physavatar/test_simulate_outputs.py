"""PhysAvatar's result files come out whole or not at all: a writer that fails part way (a full disk, Ctrl-C) leaves
neither a half-written file nor a temporary one and keeps an earlier file at that path; ``apps.avatar simulate``
checks its output paths before simulating, and on Ctrl-C keeps what it finished and exits 130 saying so."""

from __future__ import annotations

import errno
import json
import math

import numpy as np
import pytest
import torch

import physavatar.result_files as result_files
import physavatar.simulate as simulate_module
from apps import avatar
from physavatar.cloth import ClothStepReport, SolverCloth
from physavatar.simulate import SimulationResult, render_video, write_meshes, write_npz, write_stats_json
from pienerf.output_files import atomic_path

pytestmark = pytest.mark.data  # the default garment of apps.avatar comes from the shared folder when present

EARLIER = b"an earlier, complete result"


def _result(frames: int = 3) -> SimulationResult:
    """A tiny sequence: a two-triangle cloth sliding over a tetrahedron."""
    cloth = torch.tensor([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    body = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]], dtype=torch.float64)
    shift = torch.arange(frames + 1, dtype=torch.float64)[:, None, None] * torch.tensor([0.01, 0.0, 0.0])
    step = ClothStepReport(
        newton_iterations=3, converged=True, min_distance_body=0.01, min_distance_self=math.inf, contacts=0
    )
    return SimulationResult(
        garment_frames=cloth + shift,
        body_frames=body + 0.0 * shift,
        garment_faces=torch.tensor([[0, 1, 2], [1, 3, 2]]),
        body_faces=torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
        boundary_index=torch.tensor([0]),
        fps=25.0,
        stats=[step] * frames,
        wall_time=[0.1] * frames,
    )


def _disk_full() -> OSError:
    return OSError(errno.ENOSPC, "No space left on device")


def _leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if ".partial" in p.name)


def test_npz_writer_failing_mid_write_keeps_the_earlier_file(monkeypatch, tmp_path):
    target = tmp_path / "sequence.npz"
    target.write_bytes(EARLIER)

    def savez_then_fail(file, **arrays):
        file.write(b"PK\x03\x04 the start of an archive")
        raise _disk_full()

    monkeypatch.setattr(result_files.np, "savez_compressed", savez_then_fail)
    with pytest.raises(OSError, match="No space left"):
        write_npz(_result(), target, staging=atomic_path)
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


def test_stats_writer_failing_mid_write_keeps_the_earlier_file(monkeypatch, tmp_path):
    target = tmp_path / "stats.json"
    target.write_bytes(EARLIER)

    def dump_then_fail(value, file, **options):
        file.write('{"summary": {"frames": ')
        raise _disk_full()

    monkeypatch.setattr(result_files.json, "dump", dump_then_fail)
    with pytest.raises(OSError, match="No space left"):
        write_stats_json(_result(), target, staging=atomic_path)
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


def test_mesh_writer_failing_mid_write_keeps_the_finished_and_the_earlier_meshes(monkeypatch, tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / "garment_0001.obj").write_bytes(EARLIER)
    export = simulate_module.trimesh.Trimesh.export
    calls = []

    def export_then_fail(mesh, path, *args, **options):
        calls.append(path)
        if len(calls) == 2:
            with open(path, "w") as file:
                file.write("v 0 1 0\nv 1 1")
            raise _disk_full()
        return export(mesh, path, *args, **options)

    monkeypatch.setattr(simulate_module.trimesh.Trimesh, "export", export_then_fail)
    with pytest.raises(OSError, match="No space left"):
        write_meshes(_result(), folder, "obj", staging=atomic_path)
    assert (folder / "garment_0001.obj").read_bytes() == EARLIER
    assert sorted(p.name for p in folder.iterdir()) == ["garment_0000.obj", "garment_0001.obj"]
    assert (folder / "garment_0000.obj").read_text().count("\nf ") == 2  # the frame before is whole


def test_video_writer_interrupted_mid_write_keeps_the_earlier_video(device, monkeypatch, tmp_path):
    target = tmp_path / "video.mp4"
    target.write_bytes(EARLIER)
    shade = simulate_module.shade
    frames = []

    def shade_then_interrupt(*args, **options):
        frames.append(1)
        if len(frames) == 3:  # two frames went to the encoder
            raise KeyboardInterrupt
        return shade(*args, **options)

    monkeypatch.setattr(simulate_module, "shade", shade_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        render_video(_result(), target, size=(32, 32), staging=atomic_path)
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


def _interrupt_step(monkeypatch, finished: int) -> None:
    """Ctrl-C inside the step after ``finished`` steps."""
    step = SolverCloth.step
    calls = []

    def step_then_interrupt(self, *args, **options):
        calls.append(1)
        if len(calls) > finished:
            raise KeyboardInterrupt
        return step(self, *args, **options)

    monkeypatch.setattr(SolverCloth, "step", step_then_interrupt)


def test_ctrl_c_in_the_simulation_writes_the_finished_frames_and_exits_130(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "video.mp4").write_bytes(EARLIER)
    _interrupt_step(monkeypatch, finished=2)
    assert avatar.main(["simulate", "--smoke", "--out", str(out), "--device", device]) == 130
    error = capsys.readouterr().err
    last = error.strip().splitlines()[-1]
    assert "interrupted after 2 of 3 steps" in last and "holds the frames finished before it" in last, error
    assert "Traceback" not in error
    sequence = np.load(out / "sequence.npz")
    assert sequence["garment_frames"].shape[0] == 3 and sequence["body_frames"].shape[0] == 3
    assert len(json.loads((out / "stats.json").read_text())["steps"]) == 2
    assert (out / "video.mp4").read_bytes() == EARLIER, "no video of a stopped run; the earlier one is kept"
    assert _leftovers(out) == []


def test_ctrl_c_before_the_first_step_finished_writes_nothing(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"
    _interrupt_step(monkeypatch, finished=0)
    assert avatar.main(["simulate", "--smoke", "--out", str(out), "--device", device]) == 130
    assert "interrupted before the first step finished: nothing written" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_ctrl_c_while_writing_the_video_keeps_the_finished_files(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"

    def interrupt(*args, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulate_module, "shade", interrupt)
    assert avatar.main(["simulate", "--smoke", "--out", str(out), "--device", device]) == 130
    error = capsys.readouterr().err
    last = error.strip().splitlines()[-1]
    assert last.startswith("interrupted while writing the results; kept") and "sequence.npz, stats.json" in last
    assert "the file in progress was not written" in last and "Traceback" not in error
    assert np.load(out / "sequence.npz")["garment_frames"].shape[0] == 4
    assert len(json.loads((out / "stats.json").read_text())["steps"]) == 3
    assert not (out / "video.mp4").exists() and _leftovers(out) == []


def test_a_full_disk_while_writing_exits_1_with_one_clear_line(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"

    def disk_full(value, file, **options):
        raise _disk_full()

    monkeypatch.setattr(result_files.json, "dump", disk_full)
    assert avatar.main(["simulate", "--smoke", "--out", str(out), "--device", device]) == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "No space left on device" in lines[0] and f"kept {out}/sequence.npz" in lines[0]
    assert sorted(p.name for p in out.iterdir()) == ["sequence.npz"]


def test_a_result_path_taken_by_a_folder_is_refused_before_the_simulation(tmp_path, capsys):
    out = tmp_path / "out"
    (out / "stats.json").mkdir(parents=True)
    assert avatar.main(["simulate", "--smoke", "--out", str(out), "--device", "cpu"]) == 2
    error = capsys.readouterr().err
    assert f"error: {out / 'stats.json'} is a folder where a result file goes" in error
    assert "step 1/" not in error  # nothing simulated
    assert sorted(p.name for p in out.iterdir()) == ["stats.json"]
