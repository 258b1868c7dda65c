"""Procedural motions and BVH reading/writing with retargeting."""

import math

import pytest
import torch

from kernels import backend
from physavatar.body import MOTIONS, Motion, Skeleton, jump, load_bvh, named_motion, save_bvh, turn, walk

MAX_ANGULAR_SPEED = 20.0  # rad/s, about the peak knee extension speed of a human jump


@pytest.fixture(scope="module")
def skeleton() -> Skeleton:
    return Skeleton.mannequin()


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_motion_starts_at_rest_and_stays_smooth(skeleton, name):
    motion = MOTIONS[name](skeleton)
    assert motion.fps == 25.0
    eye = torch.eye(3, dtype=motion.rotations.dtype)
    assert torch.equal(motion.rotations[0], eye.expand(22, 3, 3))
    assert torch.equal(motion.root_translation[0], torch.zeros(3, dtype=motion.root_translation.dtype))
    speed = motion.angular_speeds()
    assert speed.max() < MAX_ANGULAR_SPEED
    assert speed[0].max() < 0.1  # eases out of rest: the first frame moves far slower than the motion
    positions = motion.joint_positions(skeleton)
    velocity = (positions[1:] - positions[:-1]) * motion.fps
    assert velocity[0].abs().max() < 0.05
    acceleration = (velocity[1:] - velocity[:-1]) * motion.fps
    assert acceleration.abs().max() < 150.0  # m/s²: velocities are continuous, no jumps between frames


def test_walk_advances_the_root_forward(skeleton):
    motion = walk(skeleton, duration=4.0)
    z = motion.root_translation[:, 2]
    assert (z[1:] >= z[:-1]).all()
    assert z[-1] > 2.5
    assert motion.root_translation[:, 0].abs().max() < 1e-12


def test_turn_rotates_the_root_about_y_by_a_full_turn(skeleton):
    motion = turn(skeleton, duration=3.0)
    r = motion.rotations[:, 0]
    yaw = torch.atan2(r[:, 0, 2], r[:, 2, 2])
    step = torch.remainder(yaw[1:] - yaw[:-1] + math.pi, 2 * math.pi) - math.pi
    assert step.sum() >= math.pi
    assert step.sum() == pytest.approx(2 * math.pi, abs=1e-9)
    assert torch.allclose(r[:, 1, 1], torch.ones_like(r[:, 1, 1]))  # about y only
    assert motion.root_translation.abs().max() == 0.0


def test_raise_lifts_the_wrists_above_the_shoulders(skeleton):
    motion = MOTIONS["raise"](skeleton, amplitude=1.2)
    pos = motion.joint_positions(skeleton)[motion.num_frames // 2]
    for side in ("left", "right"):
        assert pos[skeleton.index(f"{side}_wrist"), 1] > pos[skeleton.index(f"{side}_shoulder"), 1]


def test_jump_leaves_the_ground_and_keeps_feet_out_of_it(skeleton):
    motion = jump(skeleton, amplitude=0.12)
    assert motion.root_translation[:, 1].max() == pytest.approx(0.12, abs=0.005)
    ankle = motion.joint_positions(skeleton)[:, skeleton.index("left_ankle"), 1]
    rest = skeleton.rest_positions[skeleton.index("left_ankle"), 1]
    assert ankle.min() > rest - 0.005
    assert ankle.max() > rest + 0.1
    with pytest.raises(ValueError, match="duration must exceed"):
        jump(skeleton, duration=1.0)


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_bvh_round_trip_reproduces_joint_positions(skeleton, name, tmp_path, device):
    skel = Skeleton(
        skeleton.names,
        skeleton.parents,
        *(t.to(backend.torch_device()) for t in (skeleton.rest_positions, skeleton.rest_tails)),
    )
    motion = MOTIONS[name](skel, duration=2.5)
    save_bvh(motion, tmp_path / "clip.bvh", skel)
    loaded = load_bvh(tmp_path / "clip.bvh", skel)
    assert loaded.num_frames == motion.num_frames and loaded.fps == pytest.approx(motion.fps)
    error = (loaded.joint_positions(skel) - motion.joint_positions(skel)).abs().max()
    assert error < 1e-4


def _mixamo_file(skeleton, tmp_path) -> tuple[Motion, str]:
    motion = walk(skeleton, duration=1.0)
    save_bvh(motion, tmp_path / "ours.bvh", skeleton)
    text = (tmp_path / "ours.bvh").read_text()
    names = {"pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
             "head": "Head"}  # fmt: skip
    limbs = {"collar": "Shoulder", "shoulder": "Arm", "elbow": "ForeArm", "wrist": "Hand", "hip": "UpLeg",
             "knee": "Leg", "ankle": "Foot", "foot": "ToeBase"}  # fmt: skip
    for side, prefix in (("left", "Left"), ("right", "Right")):
        names.update({f"{side}_{k}": f"{prefix}{v}" for k, v in limbs.items()})
    for ours, theirs in names.items():
        text = text.replace(f"ROOT {ours}\n", f"ROOT mixamorig:{theirs}\n").replace(
            f"JOINT {ours}\n", f"JOINT mixamorig:{theirs}\n"
        )
    return motion, text


def test_bvh_with_mixamo_names_in_inches_is_retargeted(skeleton, tmp_path):
    motion, text = _mixamo_file(skeleton, tmp_path)
    lines = text.splitlines()
    scale = 1.0 / 2.54  # rewrite the centimetre file in inches: the loader must find the unit itself
    header_end = lines.index("MOTION")
    out = []
    for i, line in enumerate(lines):
        tokens = line.split()
        if tokens[:1] == ["OFFSET"]:
            line = line[: line.index("OFFSET")] + "OFFSET " + " ".join(f"{float(x) * scale:.8f}" for x in tokens[1:])
        elif i > header_end + 2:
            values = [float(x) for x in tokens]
            line = " ".join(f"{x:.8f}" for x in [v * scale for v in values[:3]] + values[3:])
        out.append(line)
    (tmp_path / "mixamo.bvh").write_text("\n".join(out) + "\n")
    loaded = load_bvh(tmp_path / "mixamo.bvh", skeleton)
    error = (loaded.joint_positions(skeleton) - motion.joint_positions(skeleton)).abs().max()
    assert error < 1e-4


def test_bvh_missing_required_joint_is_named(skeleton, tmp_path):
    _, text = _mixamo_file(skeleton, tmp_path)
    (tmp_path / "bad.bvh").write_text(text.replace("mixamorig:LeftForeArm", "mixamorig:LeftLowerArm"))
    with pytest.raises(ValueError, match=r"no BVH joint for left_elbow \(as 'LeftForeArm'\).*name_map"):
        load_bvh(tmp_path / "bad.bvh", skeleton)


def test_malformed_bvh_errors_name_the_line(skeleton, tmp_path):
    save_bvh(walk(skeleton, duration=1.0), tmp_path / "ok.bvh", skeleton)
    lines = (tmp_path / "ok.bvh").read_text().splitlines()
    motion_line = lines.index("MOTION")
    (tmp_path / "no_motion.bvh").write_text("\n".join(lines[:motion_line]) + "\n")
    with pytest.raises(ValueError, match=rf"no_motion\.bvh:{motion_line}: no MOTION section"):
        load_bvh(tmp_path / "no_motion.bvh", skeleton)
    frame = 3
    bad = list(lines)
    bad[motion_line + 3 + frame] += " 0.0"
    (tmp_path / "extra.bvh").write_text("\n".join(bad) + "\n")
    with pytest.raises(ValueError, match=rf"extra\.bvh:{motion_line + 4 + frame}: frame 3 has 70 values but the "
                       "HIERARCHY declares 69 channels"):  # fmt: skip
        load_bvh(tmp_path / "extra.bvh", skeleton)
    bad = [line.replace("CHANNELS 3", "CHANNELS 4") if "left_knee" in lines[i - 3] else line
           for i, line in enumerate(lines)]  # fmt: skip
    (tmp_path / "channels.bvh").write_text("\n".join(bad) + "\n")
    with pytest.raises(ValueError, match=r"channels\.bvh:\d+: CHANNELS of 'left_knee' must list 4"):
        load_bvh(tmp_path / "channels.bvh", skeleton)


def test_bad_motion_arguments_raise(skeleton):
    with pytest.raises(ValueError, match="rotations must have shape"):
        Motion(torch.zeros(3, 21, 3, 3), torch.zeros(3, 3), 25.0, skeleton.names)
    with pytest.raises(ValueError, match="fps must be positive"):
        walk(skeleton, fps=0.0)
    other = Skeleton(skeleton.names[:2], skeleton.parents[:2], torch.zeros(2, 3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="made for another skeleton"):
        walk(skeleton).joint_positions(other)


def test_named_motion_keeps_its_clip_or_stretches_it_to_the_steps(skeleton):
    clip = named_motion("turn", skeleton, steps=10)
    assert torch.equal(clip.rotations, turn(skeleton).rotations)  # 3 s hold 75 steps: the clip's own timing
    longer = named_motion("turn", skeleton, steps=100)
    assert longer.num_frames == 101 and longer.fps == 25.0
    with pytest.raises(ValueError, match="motion must be one of walk, turn, raise, jump, got 'dance'"):
        named_motion("dance", skeleton, steps=10)
