"""Bad BVH files end in a ``ValueError`` naming the file and line, at load time, never in the solver later."""

import random

import pytest
import torch

from apps import avatar
from physavatar.body import MAX_BVH_FRAMES, Motion, Skeleton, load_bvh, save_bvh, walk


@pytest.fixture(scope="module")
def skeleton() -> Skeleton:
    return Skeleton.mannequin()


@pytest.fixture(scope="module")
def clip_lines(skeleton, tmp_path_factory) -> list[str]:
    """A valid 10-frame walk as BVH lines."""
    path = tmp_path_factory.mktemp("bvh") / "walk.bvh"
    save_bvh(walk(skeleton, duration=0.4, fps=25.0), path, skeleton)
    return path.read_text().splitlines()


def _line_of(lines: list[str], start: str) -> int:
    return next(k for k, line in enumerate(lines) if line.strip().startswith(start))


def _write(tmp_path, lines: list[str], name: str = "clip.bvh"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-inf"])
def test_non_finite_channel_values_are_refused_at_load(skeleton, clip_lines, tmp_path, bad):
    lines = list(clip_lines)
    row = _line_of(lines, "Frame Time:") + 4  # the fourth frame
    values = lines[row].split()
    values[5] = bad
    lines[row] = " ".join(values)
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: frame 3 holds a value that is not finite \({bad}\)"):
        load_bvh(_write(tmp_path, lines), skeleton)


def test_non_finite_offsets_are_refused(skeleton, clip_lines, tmp_path):
    lines = list(clip_lines)
    row = _line_of(lines, "OFFSET")
    lines[row] = "OFFSET 0 nan 0"
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: OFFSET holds a value that is not finite"):
        load_bvh(_write(tmp_path, lines), skeleton)


def test_a_binary_file_names_the_file_and_line(skeleton, clip_lines, tmp_path):
    path = tmp_path / "binary.bvh"
    path.write_bytes(("\n".join(clip_lines[:3]) + "\n").encode() + bytes(range(128, 256)))
    with pytest.raises(ValueError, match=r"binary\.bvh:4: not a text BVH file"):
        load_bvh(path, skeleton)
    path.write_bytes(b"HIERARCHY\nROOT a\x00b\n")
    with pytest.raises(ValueError, match=r"binary\.bvh:2: not a text BVH file \(it holds NUL bytes\)"):
        load_bvh(path, skeleton)


@pytest.mark.parametrize("value", ["abc", "1/30", "nan", "inf", "0", "-0.04"])
def test_a_bad_frame_time_names_the_line(skeleton, clip_lines, tmp_path, value):
    lines = list(clip_lines)
    row = _line_of(lines, "Frame Time:")
    lines[row] = f"Frame Time: {value}"
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: .*(not a number of seconds|finite, positive frame)"):
        load_bvh(_write(tmp_path, lines), skeleton)


@pytest.mark.parametrize("count", [1_000_000_000_000, MAX_BVH_FRAMES + 1])
def test_a_huge_frame_count_is_refused_without_allocating(skeleton, clip_lines, tmp_path, count):
    lines = list(clip_lines)
    row = _line_of(lines, "Frames:")
    lines[row] = f"Frames: {count}"
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: 'Frames: {count}' exceeds the {MAX_BVH_FRAMES}"):
        load_bvh(_write(tmp_path, lines), skeleton)


def test_a_frame_count_beyond_the_file_names_the_header(skeleton, clip_lines, tmp_path):
    lines = list(clip_lines)
    row = _line_of(lines, "Frames:")
    frames = int(lines[row].split()[1])
    lines[row] = "Frames: 5000"
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: 'Frames: 5000' but only {frames} lines follow"):
        load_bvh(_write(tmp_path, lines), skeleton)


def test_unicode_digits_and_zero_legs_are_clear_errors(skeleton, clip_lines, tmp_path):
    lines = list(clip_lines)
    row = _line_of(lines, "Frames:")
    lines[row] = "Frames: ²"
    with pytest.raises(ValueError, match=rf"clip\.bvh:{row + 1}: expected 'Frames: <count>'"):
        load_bvh(_write(tmp_path, lines), skeleton)
    flat = [("OFFSET 0 0 0" if line.strip().startswith("OFFSET") else line) for line in clip_lines]
    with pytest.raises(ValueError, match=r"clip\.bvh: the legs of its rest pose .* pass unit_scale"):
        load_bvh(_write(tmp_path, flat), skeleton)
    with pytest.raises(ValueError, match="unit_scale must be a finite positive number"):
        load_bvh(_write(tmp_path, clip_lines), skeleton, unit_scale=float("nan"))


_ODD_TOKENS = ["abc", "{", "}", "JOINT", "ROOT", "End", "Site", "CHANNELS", "MOTION", "Frames:", "99999999999999",
               "²", "Xrotation", "Wposition", "0x10"]  # fmt: skip
_ODD_NUMBERS = ["nan", "inf", "-inf", "1e400", "-1", "0", "1e-300", "3.5", "720", "-1e30"]


def _mutate(lines: list[str], rng: random.Random) -> str:
    """One to three edits: a token replaced (by a number, more often in the frames), a line dropped, repeated or
    cut short, or the file truncated."""
    lines = list(lines)
    motion = next(k for k, line in enumerate(lines) if line.startswith("Frame Time:"))
    for _ in range(rng.randint(1, 3)):
        in_frames = rng.random() < 0.5
        row = rng.randrange(motion + 1, len(lines)) if in_frames else rng.randrange(len(lines))
        action = rng.random()
        if action < 0.6:
            tokens = lines[row].split() or [""]
            odd = _ODD_NUMBERS if in_frames or rng.random() < 0.5 else _ODD_TOKENS
            tokens[rng.randrange(len(tokens))] = rng.choice(odd)
            lines[row] = " ".join(tokens)
        elif action < 0.7:
            del lines[row]
        elif action < 0.8:
            lines.insert(row, lines[rng.randrange(len(lines))])
        elif action < 0.9:
            lines = lines[: rng.randrange(len(lines))]
        else:
            tokens = lines[row].split()
            lines[row] = " ".join(tokens[: rng.randrange(len(tokens) + 1)])
        if len(lines) <= motion + 1:
            break
    return "\n".join(lines) + "\n"


def test_fuzzed_bvh_files_load_or_fail_clearly(skeleton, clip_lines, tmp_path):
    rng = random.Random(11)
    path = tmp_path / "fuzz.bvh"
    outcomes = {"loaded": 0, "refused": 0}
    for case in range(150):
        text = _mutate(clip_lines, rng)
        if case % 10 == 9:
            raw = bytearray(text.encode())
            raw[rng.randrange(len(raw))] = rng.choice([0, 0xFF, 0xC3])
            path.write_bytes(bytes(raw))
        else:
            path.write_text(text)
        try:
            motion = load_bvh(path, skeleton)
        except ValueError as error:
            assert str(path) in str(error), f"case {case}: {error}"
            outcomes["refused"] += 1
        else:
            assert isinstance(motion, Motion)
            assert torch.isfinite(motion.rotations).all() and torch.isfinite(motion.root_translation).all()
            outcomes["loaded"] += 1
    assert outcomes["loaded"] > 5 and outcomes["refused"] > 50, outcomes


def _renamed(lines: list[str], ours: str, theirs: str) -> list[str]:
    """The clip with the joint ``ours`` called ``theirs`` in the hierarchy."""
    return [line.replace(f" {ours}", f" {theirs}") if line.strip() in (f"ROOT {ours}", f"JOINT {ours}") else line
            for line in lines]  # fmt: skip


def test_a_joint_named_differently_is_named_and_mapped(skeleton, clip_lines, tmp_path):
    path = _write(tmp_path, _renamed(clip_lines, "left_knee", "LeftLeg_2"))
    with pytest.raises(ValueError, match=r"no BVH joint for left_knee \(as 'left_knee'\).*LeftLeg_2.*name_map"):
        load_bvh(path, skeleton)
    mapped = load_bvh(path, skeleton, name_map={"left_knee": "LeftLeg_2"})
    plain = load_bvh(_write(tmp_path, clip_lines, "plain.bvh"), skeleton)
    assert torch.equal(mapped.rotations, plain.rotations)
    assert torch.equal(mapped.root_translation, plain.root_translation)


def test_the_command_line_maps_joints_and_names_a_bad_pair(device, clip_lines, tmp_path, capsys):
    path = _write(tmp_path, _renamed(clip_lines, "left_knee", "LeftLeg_2"))
    out = tmp_path / "out"
    assert avatar.main(["simulate", "--motion", str(path), "--smoke", "--device", device, "--out", str(out)]) == 2
    assert "--joint-map ours=theirs" in capsys.readouterr().err
    for bad, says in (("left_knee", "ours=theirs pairs"), ("kneee=LeftLeg_2", "'kneee', which is not one of")):
        args = ["simulate", "--motion", str(path), "--joint-map", bad, "--smoke", "--device", device, "--out", str(out)]
        assert avatar.main(args) == 2
        assert says in capsys.readouterr().err
    assert not out.exists()
