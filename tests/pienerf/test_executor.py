"""The executor on small point functions: whole-or-nothing point folders, the index, retries of a raising point and of
a worker process killed mid-point, resumption after an interruption, and the message where Ray is missing."""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
from pathlib import Path

import pytest
import torch

from pienerf.executor import POINT_FILE, ExecutorConfig, ExecutorError, completed_point, require_ray, run_points
from pienerf.output_files import staged_folder, stale_staging_folders

POINTS = {f"p{i}": {"x": i} for i in range(4)}


def square(parameters: dict, folder: Path) -> dict:
    """Writes ``x²`` to ``folder/out.txt``, returns it; with ``die`` (a marker path), kills its own process on the
    first attempt (the marker not yet there), after writing part of its folder; with ``fail``, raises."""
    (folder / "partial.txt").write_text("begun")
    if parameters.get("die") and not Path(parameters["die"]).exists():
        Path(parameters["die"]).write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    if parameters.get("fail"):
        raise ValueError(f"point with x = {parameters['x']} cannot be computed")
    (folder / "out.txt").write_text(str(parameters["x"] ** 2))
    return {"square": parameters["x"] ** 2, "pid": os.getpid()}


def interrupted_at_two(parameters: dict, folder: Path) -> dict:
    """``square``, but Ctrl-C arrives while point x = 2 is half written."""
    (folder / "partial.txt").write_text("begun")
    if parameters["x"] == 2:
        raise KeyboardInterrupt
    return square(parameters, folder)


def _snapshot(folder: Path) -> dict:
    """Every file under ``folder``: (inode, modification time in ns, bytes)."""
    return {
        p.relative_to(folder): (p.stat().st_ino, p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_points_are_written_whole_with_an_index(tmp_path):
    entries = run_points(POINTS, square, tmp_path, log=lambda line: None)
    assert [e["name"] for e in entries] == list(POINTS)
    for entry, (name, parameters) in zip(entries, POINTS.items(), strict=True):
        assert entry["status"] == "complete" and entry["attempts"] == 1
        assert entry["metrics"]["square"] == parameters["x"] ** 2
        assert (tmp_path / name / "out.txt").read_text() == str(parameters["x"] ** 2)
        assert completed_point(tmp_path / name, parameters)["metrics"]["square"] == parameters["x"] ** 2
    index = json.loads((tmp_path / "sweep.json").read_text())
    assert index["counts"] == {"complete": 4, "failed": 0, "skipped": 0} and index["executor"] == "local"
    rows = list(csv.DictReader(open(tmp_path / "sweep.csv")))
    assert [(r["name"], r["status"], r["parameter.x"], r["metric.square"]) for r in rows] == [
        (name, "complete", str(p["x"]), str(p["x"] ** 2)) for name, p in POINTS.items()
    ]
    assert not list(tmp_path.glob(".p*"))  # no staging folder left


def test_a_failing_point_is_retried_then_recorded_and_the_rest_go_on(tmp_path):
    points = {**POINTS, "p1": {"x": 1, "fail": True}}
    lines = []
    entries = run_points(points, square, tmp_path, ExecutorConfig(max_retries=1), log=lines.append)
    failed = entries[1]
    assert failed["status"] == "failed" and failed["attempts"] == 2
    assert failed["error"] == "ValueError: point with x = 1 cannot be computed"
    assert not (tmp_path / "p1").exists() and not stale_staging_folders(tmp_path / "p1")
    assert [e["status"] for e in entries] == ["complete", "failed", "complete", "complete"]
    assert any("1 failed" in line for line in lines)
    assert json.loads((tmp_path / "sweep.json").read_text())["counts"]["failed"] == 1


def test_an_interrupted_run_resumes_without_touching_finished_points(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        run_points(POINTS, interrupted_at_two, tmp_path, log=lambda line: None)
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir() and not p.name.startswith(".")) == ["p0", "p1"]
    assert not stale_staging_folders(tmp_path / "p2")  # the half-written point left nothing
    index = json.loads((tmp_path / "sweep.json").read_text())
    assert [e["name"] for e in index["points"]] == ["p0", "p1"]  # the index of the points that finished
    before = _snapshot(tmp_path / "p0") | {Path("p1") / k: v for k, v in _snapshot(tmp_path / "p1").items()}
    lines = []
    entries = run_points(POINTS, square, tmp_path, log=lines.append)
    assert [e.get("skipped_as_complete", False) for e in entries] == [True, True, False, False]
    after = _snapshot(tmp_path / "p0") | {Path("p1") / k: v for k, v in _snapshot(tmp_path / "p1").items()}
    assert after == before
    assert [(tmp_path / n / "out.txt").read_text() for n in POINTS] == ["0", "1", "4", "9"]
    assert "2 already complete" in lines[0]
    # a point whose values changed runs again; its folder is replaced whole
    changed = {**POINTS, "p3": {"x": 5}}
    entries = run_points(changed, square, tmp_path, log=lambda line: None)
    assert [e.get("skipped_as_complete", False) for e in entries] == [True, True, True, False]
    assert (tmp_path / "p3" / "out.txt").read_text() == "25"


def test_a_staged_folder_replaces_an_earlier_one_only_when_whole(tmp_path):
    target = tmp_path / "point"
    with staged_folder(target) as folder:
        (folder / "a.txt").write_text("first")
    with pytest.raises(RuntimeError), staged_folder(target) as folder:
        (folder / "a.txt").write_text("second, half written")
        raise RuntimeError("stopped")
    assert (target / "a.txt").read_text() == "first" and not stale_staging_folders(target)
    with staged_folder(target) as folder:
        (folder / "b.txt").write_text("second")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"] and not stale_staging_folders(target)


def test_without_ray_the_ray_executor_names_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails as where it is not installed
    with pytest.raises(ExecutorError, match=r"pip install -e '\.\[cluster\]'"):
        require_ray()
    with pytest.raises(ExecutorError, match="--executor ray needs Ray"):
        run_points(POINTS, square, tmp_path, ExecutorConfig(kind="ray"), log=lambda line: None)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"kind": "dask"}, "executor must be one of local, ray"),
        ({"max_retries": -1}, r"max_retries \(--retries\) must be an integer in \[0, 100\], got -1"),
        ({"device": "tpu"}, "device must be 'cpu' or 'cuda'"),
    ],
)
def test_bad_executor_settings_are_named(change, message):
    with pytest.raises(ValueError, match=message):
        ExecutorConfig(**change)


def test_ray_retries_a_point_whose_worker_was_killed(local_ray, tmp_path):
    marker = tmp_path / "killed-once"
    points = {**POINTS, "p1": {"x": 1, "die": str(marker)}}
    root = tmp_path / "sweep"
    entries = run_points(points, square, root, ExecutorConfig(kind="ray", max_retries=2), log=lambda line: None)
    assert [e["status"] for e in entries] == ["complete"] * 4
    killed = int(marker.read_text())
    assert entries[1]["attempts"] == 2 and entries[1]["pid"] != killed  # a new process finished it
    with pytest.raises(ProcessLookupError):
        os.kill(killed, 0)  # the first attempt's process is gone: a real death, not an exception
    assert [(root / n / "out.txt").read_text() for n in points] == ["0", "1", "4", "9"]
    assert not any(stale_staging_folders(root / n) for n in points)  # the killed attempt's folder was cleared
    assert json.loads((root / "p1" / POINT_FILE).read_text())["attempts"] == 2


def test_ray_records_a_point_that_keeps_failing_and_finishes_the_rest(local_ray, tmp_path):
    points = {**POINTS, "p2": {"x": 2, "fail": True}}
    entries = run_points(points, square, tmp_path, ExecutorConfig(kind="ray", max_retries=1), log=lambda line: None)
    assert [e["status"] for e in entries] == ["complete", "complete", "failed", "complete"]
    assert entries[2]["attempts"] == 2
    assert entries[2]["error"].endswith("ValueError: point with x = 2 cannot be computed")
    assert not (tmp_path / "p2").exists()
    assert [entries[i]["metrics"]["square"] for i in (0, 1, 3)] == [0, 1, 9]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine's Ray has GPUs: the refusal needs a CPU-only one")
def test_a_cuda_run_on_a_ray_without_gpus_is_refused_before_any_point(local_ray, tmp_path):
    with pytest.raises(ExecutorError, match=r"the Ray cluster has no GPU, .*ray start --num-gpus N\) or run with"):
        run_points(POINTS, square, tmp_path, ExecutorConfig(kind="ray", device="cuda"), log=lambda line: None)
    assert local_ray.is_initialized()  # a Ray this run did not start is left running
    assert not any((tmp_path / name).exists() for name in POINTS)
