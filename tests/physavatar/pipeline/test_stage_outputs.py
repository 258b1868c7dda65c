"""The PhysAvatar stages' files come out whole or not at all: every writer the stages use, failing part way (a full
disk, Ctrl-C), leaves neither a half-written file nor a temporary one and keeps an earlier file at that path;
``apps.avatar pipeline`` and the stage commands check their result paths before any work, and on Ctrl-C keep the
stages they finished and exit 130 naming the command to go on with."""

from __future__ import annotations

import builtins
import errno
import json

import matplotlib
import numpy as np
import pytest
import torch
from PIL import Image

import physavatar.result_files as result_files
from apps import avatar
from physavatar import pipeline
from physavatar.capture import CameraRig, Capture, Lighting, load_capture, write_capture
from physavatar.pipeline import stages
from physavatar.result_files import save_figure, write_arrays, write_json, write_png, write_text
from pienerf.output_files import atomic_path

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)

EARLIER = b"an earlier, complete result"


def _disk_full() -> OSError:
    return OSError(errno.ENOSPC, "No space left on device")


def _leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if ".partial" in p.name)


class _FillingDisk:
    """A file on a disk with room for ``room`` more characters (or bytes): the write that overflows it puts what
    fits and then fails as a full disk does."""

    def __init__(self, file, room: int, failure: BaseException):
        self.file, self.room, self.failure = file, room, failure

    def write(self, data):
        if len(data) > self.room:
            self.file.write(data[: self.room])
            self.room = 0
            raise self.failure
        self.room -= len(data)
        return self.file.write(data)

    def __getattr__(self, name):
        return getattr(self.file, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.file.close()


def _fill_the_disk(monkeypatch, room: int, failure: BaseException) -> None:
    """Files that :mod:`physavatar.result_files` opens take ``room`` characters, then fail with ``failure``."""
    monkeypatch.setattr(
        result_files,
        "open",
        lambda path, mode="r", **options: _FillingDisk(builtins.open(path, mode, **options), room, failure),
        raising=False,
    )


def _fail_after_a_start(monkeypatch, owner, name: str, failure: BaseException, start: bytes) -> None:
    """``owner.name(self, target, ...)`` writes ``start`` to its target and then fails with ``failure``."""

    def start_then_fail(self, target, *args, **options):
        with open(target, "wb") as file:
            file.write(start)
        raise failure

    monkeypatch.setattr(owner, name, start_then_fail)


FAILURES = {"full disk": _disk_full, "ctrl-c": KeyboardInterrupt}


@pytest.mark.parametrize("failure", FAILURES)
@pytest.mark.parametrize("writer", ["text", "json", "arrays"])
def test_a_stage_writer_failing_mid_write_keeps_the_earlier_file(monkeypatch, tmp_path, writer, failure):
    target = tmp_path / f"result.{ {'text': 'md', 'json': 'json', 'arrays': 'npz'}[writer] }"
    target.write_bytes(EARLIER)
    write = {
        "text": lambda: write_text(target, "# report\n" * 1000, atomic_path),
        "json": lambda: write_json(target, {"steps": list(range(1000))}, atomic_path),
        "arrays": lambda: write_arrays(target, atomic_path, frames=np.random.default_rng(0).random((64, 64))),
    }[writer]
    _fill_the_disk(monkeypatch, room=100, failure=FAILURES[failure]())
    with pytest.raises(type(FAILURES[failure]())):
        write()
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


@pytest.mark.parametrize("failure", FAILURES)
def test_the_png_writer_failing_mid_write_keeps_the_earlier_image(monkeypatch, tmp_path, failure):
    target = tmp_path / "relit.png"
    target.write_bytes(EARLIER)
    _fail_after_a_start(monkeypatch, Image.Image, "save", FAILURES[failure](), b"\x89PNG\r\n\x1a\n")
    with pytest.raises(type(FAILURES[failure]())):
        write_png(target, np.zeros((8, 8, 3), np.uint8), atomic_path)
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


@pytest.mark.parametrize("failure", FAILURES)
def test_the_figure_writer_failing_mid_write_keeps_the_earlier_plot(monkeypatch, tmp_path, failure):
    target = tmp_path / "chamfer.png"
    target.write_bytes(EARLIER)
    figure, axes = plt.subplots()
    axes.plot([0.0, 1.0])
    _fail_after_a_start(monkeypatch, type(figure), "savefig", FAILURES[failure](), b"\x89PNG\r\n\x1a\n")
    try:
        with pytest.raises(type(FAILURES[failure]())):
            save_figure(figure, target, atomic_path)
    finally:
        plt.close(figure)
    assert target.read_bytes() == EARLIER and _leftovers(tmp_path) == []


def test_the_stage_writers_write_whole_files_through_the_staging_step(tmp_path):
    figure, axes = plt.subplots()
    axes.plot([0.0, 1.0])
    try:
        save_figure(figure, tmp_path / "plot.png", atomic_path)
    finally:
        plt.close(figure)
    write_png(tmp_path / "image.png", np.full((4, 6, 3), 200, np.uint8), atomic_path)
    write_arrays(tmp_path / "arrays", atomic_path, x=np.arange(3))  # no suffix added
    write_json(tmp_path / "record.json", {"a": 1}, atomic_path)
    write_text(tmp_path / "report.md", "κ_s\n", atomic_path)
    assert Image.open(tmp_path / "plot.png").format == "PNG"
    assert np.asarray(Image.open(tmp_path / "image.png")).shape == (4, 6, 3)
    assert np.load(tmp_path / "arrays")["x"].tolist() == [0, 1, 2]
    assert json.loads((tmp_path / "record.json").read_text()) == {"a": 1}
    assert (tmp_path / "report.md").read_text(encoding="utf-8") == "κ_s\n"
    assert _leftovers(tmp_path) == []
    with pytest.raises(ValueError, match=r"uint8 \[H, W, 3\]"):
        write_png(tmp_path / "bad.png", np.zeros((4, 6, 3)), atomic_path)


def _tiny_capture(frames: int = 2, cameras: int = 2) -> Capture:
    rig = CameraRig.ring(cameras, 2.0, 0.2, (0.0, 0.8, 0.0), 16, 16)
    images = torch.rand(frames, cameras, 16, 16, 3, generator=torch.Generator().manual_seed(0))
    return Capture(images, images[..., 0] > 0.5, rig, 25.0, Lighting())


def test_the_capture_writer_failing_mid_image_keeps_the_earlier_files(monkeypatch, tmp_path):
    folder = tmp_path / "capture"
    (folder / "images").mkdir(parents=True)
    (folder / "images" / "t0000_c01.png").write_bytes(EARLIER)
    (folder / "transforms.json").write_bytes(EARLIER)
    save = Image.Image.save
    calls = []

    def save_then_fail(image, target, *args, **options):
        calls.append(target)
        if len(calls) == 3:  # image and mask of camera 0 are written; camera 1's image fails part way
            with open(target, "wb") as file:
                file.write(b"\x89PNG\r\n\x1a\n")
            raise _disk_full()
        return save(image, target, *args, **options)

    monkeypatch.setattr(Image.Image, "save", save_then_fail)
    with pytest.raises(OSError, match="No space left"):
        write_capture(_tiny_capture(), folder, truth={"albedo": torch.ones(4, 3)}, staging=atomic_path)
    assert (folder / "images" / "t0000_c01.png").read_bytes() == EARLIER
    assert (folder / "transforms.json").read_bytes() == EARLIER, "the index is written last"
    assert np.asarray(Image.open(folder / "images" / "t0000_c00.png")).shape == (16, 16, 3)  # the one before: whole
    assert not (folder / "truth.npz").exists() and _leftovers(folder) == []


def test_the_capture_writer_failing_mid_truth_keeps_the_earlier_index(monkeypatch, tmp_path):
    folder = tmp_path / "capture"
    folder.mkdir()
    (folder / "truth.npz").write_bytes(EARLIER)
    (folder / "transforms.json").write_bytes(EARLIER)
    _fill_the_disk(monkeypatch, room=200, failure=_disk_full())
    truth = {"garment_frames": torch.rand(2, 500, 3, generator=torch.Generator().manual_seed(1))}
    with pytest.raises(OSError, match="No space left"):
        write_capture(_tiny_capture(), folder, truth=truth, staging=atomic_path)
    assert (folder / "truth.npz").read_bytes() == EARLIER and (folder / "transforms.json").read_bytes() == EARLIER
    assert len(list((folder / "images").iterdir())) == 4 and _leftovers(folder) == []


def test_a_truth_that_cannot_be_stored_is_refused_before_any_file(tmp_path):
    with pytest.raises(ValueError, match="truth values must be tensors"):
        write_capture(_tiny_capture(), tmp_path / "capture", truth={"note": object()}, staging=atomic_path)
    assert not (tmp_path / "capture").exists()


def test_the_staged_capture_reads_back(tmp_path):
    capture = _tiny_capture()
    write_capture(capture, tmp_path / "capture", truth={"albedo": torch.ones(4, 3)}, staging=atomic_path)
    loaded = load_capture(tmp_path / "capture")
    assert torch.equal(loaded.masks, capture.masks)
    assert torch.equal(loaded.images, torch.round(capture.images * 255) / 255)
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    ("command", "taken", "kind", "message"),
    [
        ("pipeline", "evaluate/report.md", "folder", "is a folder where a result file goes"),
        ("pipeline", "track", "file", "is a file where a result folder goes"),
        ("capture", "capture/images", "file", "is a file where a result folder goes"),
        ("estimate", "estimate/estimate.json", "folder", "is a folder where a result file goes"),
    ],
)
def test_a_result_path_taken_is_refused_before_any_work(tmp_path, capsys, command, taken, kind, message):
    out = tmp_path / "out"
    path = out / taken
    if kind == "folder":
        path.mkdir(parents=True)
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(EARLIER)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert avatar.main([command, "--smoke", "--out", str(out), "--device", "cpu"]) == 2
    error = capsys.readouterr().err
    assert f"error: {path} {message}; remove it or pass another --out" in error
    assert "[capture]" not in error  # no stage started
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before


def test_ctrl_c_in_the_pipeline_keeps_the_finished_stages_and_exits_130(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "track").mkdir(parents=True)
    (out / "track" / "tracked.npz").write_bytes(EARLIER)

    def interrupted_tracking(*args, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(stages, "track", interrupted_tracking)
    assert avatar.main(["pipeline", "--smoke", "--out", str(out), "--device", device]) == 130
    error = capsys.readouterr().err
    last = error.strip().splitlines()[-1]
    assert last == (
        f"interrupted in the track stage (2 of 6) (Ctrl-C); kept in {out}: capture/ (whole); no file was left "
        f"half-written; to go on, run python -m apps.avatar track --out {out} --smoke and the stages after it"
    ), error
    assert "[capture] done in" in error and "Traceback" not in error
    film = load_capture(out / "capture")
    assert film.images.shape[:2] == (6, 4)
    with np.load(out / "capture" / "inputs.npz") as inputs:
        assert inputs["body_frames"].shape[0] == 6
    assert (out / "track" / "tracked.npz").read_bytes() == EARLIER, "the earlier tracking is kept"
    written = {p.relative_to(out).as_posix() for p in out.rglob("*")}
    listed = {name.rstrip("/") for name in pipeline.OUTPUTS["capture"]}
    assert {name for name in written if name.startswith("capture/") and name.count("/") == 1} == listed - {"capture"}
    assert _leftovers(out) == []


def test_a_full_disk_in_a_stage_exits_1_with_one_clear_line(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"
    savez = np.savez_compressed

    def inputs_fail(file, **arrays):
        if "first_vertices" in arrays:  # the capture's last file
            file.write(b"PK\x03\x04")
            raise _disk_full()
        return savez(file, **arrays)

    monkeypatch.setattr(result_files.np, "savez_compressed", inputs_fail)
    assert avatar.main(["capture", "--smoke", "--out", str(out), "--device", device]) == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, lines
    assert lines[0] == (
        "error: capture failed ([Errno 28] No space left on device); kept in "
        f"{out}: capture/images/ (24 files), capture/masks/ (24 files), capture/truth.npz, capture/transforms.json; "
        "no file was left half-written"
    )
    assert not (out / "capture" / "inputs.npz").exists() and _leftovers(out) == []
    assert len(load_capture(out / "capture").images) == 6  # what was written is whole


def test_ctrl_c_in_a_stage_command_keeps_the_earlier_files_and_exits_130(device, monkeypatch, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "capture").mkdir(parents=True)
    (out / "capture" / "transforms.json").write_bytes(EARLIER)

    def interrupted_rendering(*args, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(stages, "render_capture", interrupted_rendering)
    assert avatar.main(["capture", "--smoke", "--out", str(out), "--device", device]) == 130
    error = capsys.readouterr().err
    assert error.strip().splitlines()[-1] == (
        f"interrupted: the capture stage stopped (Ctrl-C); nothing written to {out}; no file was left half-written"
    )
    assert (out / "capture" / "transforms.json").read_bytes() == EARLIER and _leftovers(out) == []
