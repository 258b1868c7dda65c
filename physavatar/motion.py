"""Body motions that drive the garment: procedural clips and BVH motion files (PhysAvatar §3.2 "Animation").

A :class:`Motion` is a sequence of poses of a :class:`~physavatar.body.Skeleton`: local joint
rotations and a root displacement per frame. The procedural clips (:func:`walk`, :func:`turn`,
:func:`raise_arms`, :func:`jump`) start exactly in the rest pose at rest (zero velocity), so a garment
draped on the rest body can start at frame 0 with zero velocity as the paper assumes, and their joint
angles are at least C1 in time (continuous angular velocities). Rotation conventions are those of
:mod:`physavatar.body`: y up, facing +z, rotations in world axes at rest.

BVH files are read with per-joint Euler orders from their CHANNELS lines, retargeted onto our skeleton
by joint names (:data:`BVH_NAME_MAPS`) and by transferring each bone's world rotation; BVH files are
written with ZXY Euler channels in centimetres.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from physavatar.body import Skeleton, axis_angle_to_matrix

__all__ = [
    "BVH_NAME_MAPS",
    "MAX_BVH_FRAMES",
    "MOTIONS",
    "REQUIRED_JOINTS",
    "Motion",
    "jump",
    "load_bvh",
    "named_motion",
    "raise_arms",
    "save_bvh",
    "turn",
    "walk",
]

GRAVITY = 9.81  # m/s^2
_KNEE_EASE = 0.004  # m, see jump()


@dataclass(frozen=True, eq=False)
class Motion:
    """Poses of a skeleton over time.

    Attributes:
        rotations: [T, J, 3, 3] local joint rotations (see :meth:`Skeleton.joint_transforms`).
        root_translation: [T, 3] displacement of the root joint from its rest position, metres.
        fps: frames per second.
        joint_names: the skeleton's joint names, in the order of ``rotations``.
    """

    rotations: torch.Tensor
    root_translation: torch.Tensor
    fps: float
    joint_names: tuple[str, ...]

    def __post_init__(self):
        t, j = self.rotations.shape[0], len(self.joint_names)
        if tuple(self.rotations.shape) != (t, j, 3, 3):
            raise ValueError(f"rotations must have shape [T, {j}, 3, 3], got {list(self.rotations.shape)}")
        if tuple(self.root_translation.shape) != (t, 3):
            raise ValueError(f"root_translation must have shape [{t}, 3], got {list(self.root_translation.shape)}")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    @property
    def duration(self) -> float:
        """Time from the first to the last frame, seconds."""
        return (self.num_frames - 1) / self.fps

    def joint_positions(self, skeleton: Skeleton) -> torch.Tensor:
        """[T, J, 3] world joint positions of every frame, metres."""
        self._check_skeleton(skeleton)
        return skeleton.joint_positions(self.rotations, self.root_translation)

    def angular_speeds(self) -> torch.Tensor:
        """[T-1, J] angle of each joint's local rotation change between frames times fps, rad/s."""
        relative = self.rotations[:-1].transpose(-1, -2) @ self.rotations[1:]
        cos = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
        return torch.arccos(cos) * self.fps

    def _check_skeleton(self, skeleton: Skeleton):
        if tuple(skeleton.names) != tuple(self.joint_names):
            raise ValueError("the motion was made for another skeleton: its joint names differ from the skeleton's")


# --- procedural motions -------------------------------------------------------------------------------


def _ease(t: np.ndarray, start: float, end: float) -> np.ndarray:
    """Quintic smoothstep from 0 at ``start`` to 1 at ``end`` with zero first and second derivatives at both."""
    u = np.clip((t - start) / (end - start), 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _quintic(t: np.ndarray, t0: float, t1: float, start: tuple, end: tuple) -> np.ndarray:
    """Quintic polynomial on [t0, t1] matching (position, velocity, acceleration) ``start`` and ``end``."""
    h = t1 - t0
    rows = []
    for tau in (0.0, h):
        rows.append([tau**k for k in range(6)])
        rows.append([k * tau ** (k - 1) if k >= 1 else 0.0 for k in range(6)])
        rows.append([k * (k - 1) * tau ** (k - 2) if k >= 2 else 0.0 for k in range(6)])
    coeff = np.linalg.solve(np.array(rows), np.array([*start, *end], dtype=float))
    tau = t - t0
    return sum(c * tau**k for k, c in enumerate(coeff))


def _times(duration: float, fps: float, minimum: float = 0.0) -> np.ndarray:
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if not duration > minimum:
        raise ValueError(f"duration must exceed {minimum} s for this motion, got {duration}")
    return np.arange(int(round(duration * fps)) + 1) / fps


class _PoseTrack:
    """Axis-angle tracks [T, J, 3] filled joint by joint, turned into a :class:`Motion`."""

    def __init__(self, skeleton: Skeleton, times: np.ndarray, fps: float):
        self.skeleton, self.times, self.fps = skeleton, times, fps
        self.axis_angle = np.zeros((len(times), skeleton.num_joints, 3))
        self.root = np.zeros((len(times), 3))
        self.rest = skeleton.rest_positions.cpu().numpy()

    def rotate(self, joint: str, axis, angle: np.ndarray):
        """Add a rotation of ``angle`` [T] radians about the world-at-rest ``axis`` to ``joint``."""
        axis = np.asarray(axis, dtype=float)
        self.axis_angle[:, self.skeleton.index(joint)] += angle[:, None] * axis / np.linalg.norm(axis)

    def bend_axis(self, joint: str, child: str) -> np.ndarray:
        """Axis that swings the bone ``joint``→``child`` forward (+z) for a positive angle."""
        bone = self.rest[self.skeleton.index(child)] - self.rest[self.skeleton.index(joint)]
        return np.cross(bone, [0.0, 0.0, 1.0])

    def motion(self) -> Motion:
        dtype = self.skeleton.rest_positions.dtype
        return Motion(
            axis_angle_to_matrix(torch.as_tensor(self.axis_angle, dtype=dtype)),
            torch.as_tensor(self.root, dtype=dtype),
            float(self.fps),
            tuple(self.skeleton.names),
        )


def walk(
    skeleton: Skeleton, duration: float = 4.0, fps: float = 25.0, amplitude: float = 1.0, cadence: float = 0.9
) -> Motion:
    """Walk forward (+z): a sinusoidal gait that fades in from the rest pose over the first second.

    Args:
        skeleton: the skeleton to animate.
        duration: seconds.
        fps: frames per second.
        amplitude: scale of the joint swings and of the stride (1 = a normal walk, about 0.45 rad hip swing).
        cadence: gait cycles (two steps) per second.

    Returns:
        The motion; the root advances by stride × cadence ≈ 1.1 m/s at full amplitude.
    """
    t = _times(duration, fps)
    track = _PoseTrack(skeleton, t, fps)
    fade = _ease(t, 0.0, min(1.0, duration / 2))
    phase = 2.0 * math.pi * cadence * t
    x = [1.0, 0.0, 0.0]
    for side, sign in (("left", 1.0), ("right", -1.0)):
        s = np.sin(phase) * sign
        swing = np.maximum(0.0, np.cos(phase - 0.4 if sign > 0 else phase - 0.4 + math.pi))
        track.rotate(f"{side}_hip", x, -0.45 * amplitude * fade * s)
        track.rotate(f"{side}_knee", x, 0.9 * amplitude * fade * swing**2)
        track.rotate(f"{side}_ankle", x, -0.15 * amplitude * fade * s)
        track.rotate(f"{side}_shoulder", x, 0.35 * amplitude * fade * s)
        track.rotate(f"{side}_elbow", track.bend_axis(f"{side}_elbow", f"{side}_wrist"), 0.25 * amplitude * fade)
    track.rotate("spine2", [0.0, 1.0, 0.0], 0.08 * amplitude * fade * np.sin(phase))
    stride = 1.25 * amplitude  # m per gait cycle
    speed = stride * cadence * fade
    track.root[:, 2] = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) / fps)])
    track.root[:, 1] = -0.02 * amplitude * fade * np.sin(phase) ** 2
    return track.motion()


def turn(skeleton: Skeleton, duration: float = 3.0, fps: float = 25.0, amplitude: float = 1.0) -> Motion:
    """Twirl in place about the vertical axis with the arms lifted, easing in and out of the turn.

    Args:
        skeleton: the skeleton to animate.
        duration: seconds.
        fps: frames per second.
        amplitude: number of full turns (counter-clockwise seen from above).

    Returns:
        The motion; the root yaw goes from 0 to 2π·amplitude with zero angular velocity at both ends.
    """
    t = _times(duration, fps)
    track = _PoseTrack(skeleton, t, fps)
    track.rotate("pelvis", [0.0, 1.0, 0.0], 2.0 * math.pi * amplitude * _ease(t, 0.0, duration))
    lift = _ease(t, 0.0, 0.3 * duration) - _ease(t, 0.7 * duration, duration)
    track.rotate("left_shoulder", [0.0, 0.0, 1.0], 0.5 * lift)
    track.rotate("right_shoulder", [0.0, 0.0, -1.0], 0.5 * lift)
    return track.motion()


def raise_arms(skeleton: Skeleton, duration: float = 3.0, fps: float = 25.0, amplitude: float = 1.2) -> Motion:
    """Raise both arms sideways and lower them again, angle(t) = amplitude · sin²(πt / duration).

    Args:
        skeleton: the skeleton to animate.
        duration: seconds.
        fps: frames per second.
        amplitude: peak shoulder abduction from the rest A-pose, radians (π/4 brings the arms horizontal).
    """
    t = _times(duration, fps)
    track = _PoseTrack(skeleton, t, fps)
    angle = amplitude * np.sin(math.pi * t / duration) ** 2
    for side, sign in (("left", 1.0), ("right", -1.0)):
        track.rotate(f"{side}_shoulder", [0.0, 0.0, sign], 0.85 * angle)
        track.rotate(f"{side}_collar", [0.0, 0.0, sign], 0.15 * angle)
    return track.motion()


def _leg_angles(hip_ankle: float, thigh: float, shin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sagittal two-bone IK: hip, knee and ankle rotations (about +x) that keep the foot flat below the hip."""
    alpha = np.arccos(np.clip((thigh**2 + hip_ankle**2 - shin**2) / (2.0 * thigh * hip_ankle), -1.0, 1.0))
    beta = np.arctan2(-thigh * np.sin(alpha), hip_ankle - thigh * np.cos(alpha))  # shin's forward lean
    return -alpha, alpha - beta, beta


def jump(skeleton: Skeleton, duration: float = 2.5, fps: float = 25.0, amplitude: float = 0.12) -> Motion:
    """A vertical jump: crouch, push off, ballistic flight, landing and recovery to the rest pose.

    The pelvis height follows quintic segments that match position, velocity and acceleration at each
    phase change (so the flight is an exact parabola under g = 9.81 m/s²); the legs follow by two-bone
    IK so the feet stay flat on the ground (within 4 mm) whenever the pelvis is lowered.

    Args:
        skeleton: the skeleton to animate.
        duration: seconds, at least the 1.9 s the jump takes at the default height.
        fps: frames per second.
        amplitude: height of the flight above the standing pose, metres.
    """
    if not amplitude > 0:
        raise ValueError(f"amplitude (jump height) must be positive metres, got {amplitude}")
    v0 = math.sqrt(2.0 * GRAVITY * amplitude)
    crouch, push, flight, land, recover = 0.5, 0.3, 2.0 * v0 / GRAVITY, 0.3, 0.5
    total = crouch + push + flight + land + recover
    t = _times(duration, fps, minimum=total)
    depth = 0.10 * skeleton.rest_positions[0, 1].item() / 0.98
    t1, t2 = crouch, crouch + push
    t3, t4 = t2 + flight, t2 + flight + land
    height = np.select(
        [t < t1, t < t2, t < t3, t < t4],
        [
            -depth * _ease(t, 0.0, t1),
            _quintic(t, t1, t2, (-depth, 0.0, 0.0), (0.0, v0, -GRAVITY)),
            v0 * (t - t2) - 0.5 * GRAVITY * (t - t2) ** 2,
            _quintic(t, t3, t4, (0.0, -v0, -GRAVITY), (-depth, 0.0, 0.0)),
        ],
        -depth * (1.0 - _ease(t, t4, t4 + recover)),
    )
    track = _PoseTrack(skeleton, t, fps)
    track.root[:, 1] = height
    rest = track.rest
    # How far the legs shorten: the pelvis drop δ, eased as δ²/(δ + ε) near full extension where the
    # two-bone IK angle grows like √δ and would spin the knees infinitely fast at take-off.
    drop = np.maximum(-height, 0.0)
    lowered = drop**2 / (drop + _KNEE_EASE)
    for side in ("left", "right"):
        hip, knee, ankle = (rest[skeleton.index(f"{side}_{j}")] for j in ("hip", "knee", "ankle"))
        thigh, shin = np.linalg.norm(knee - hip), np.linalg.norm(ankle - knee)
        hip_angle, knee_angle, ankle_angle = _leg_angles(np.linalg.norm(ankle - hip) - lowered, thigh, shin)
        rest_hip, rest_knee, rest_ankle = _leg_angles(np.linalg.norm(ankle - hip), thigh, shin)
        x = [1.0, 0.0, 0.0]
        track.rotate(f"{side}_hip", x, hip_angle - rest_hip)
        track.rotate(f"{side}_knee", x, knee_angle - rest_knee)
        track.rotate(f"{side}_ankle", x, ankle_angle - rest_ankle)
        swing = 0.5 * drop / depth - 0.8 * np.maximum(height, 0.0) / amplitude
        track.rotate(f"{side}_shoulder", x, swing)
    track.rotate("spine1", [1.0, 0.0, 0.0], 0.3 * drop / depth)
    return track.motion()


# --- BVH files ------------------------------------------------------------------------------------------

_SIDES = (("left", "Left"), ("right", "Right"))
_LIMBS_MIXAMO = {
    "collar": "Shoulder", "shoulder": "Arm", "elbow": "ForeArm", "wrist": "Hand",
    "hip": "UpLeg", "knee": "Leg", "ankle": "Foot", "foot": "ToeBase",
}  # fmt: skip
BVH_NAME_MAPS: dict[str, dict[str, str]] = {
    "smpl": {},
    "mixamo": {
        "pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck", "head": "Head",
        **{f"{ours}_{limb}": f"{theirs}{name}" for ours, theirs in _SIDES for limb, name in _LIMBS_MIXAMO.items()},
    },
    "cmu": {
        "pelvis": "Hips", "spine1": "LowerBack", "spine2": "Spine", "spine3": "Spine1", "neck": "Neck", "head": "Head",
        **{f"{ours}_{limb}": f"{theirs}{name}" for ours, theirs in _SIDES for limb, name in _LIMBS_MIXAMO.items()},
    },
}  # fmt: skip
"""Our joint name → BVH joint name, per naming scheme. ``smpl`` is the identity (our own files); Mixamo
names are matched after dropping a ``prefix:`` such as ``mixamorig:``. The scheme that matches most
joints of a file is used unless ``name_map`` is given."""

REQUIRED_JOINTS = tuple(
    f"{side}_{limb}" for side in ("left", "right") for limb in ("hip", "knee", "ankle", "shoulder", "elbow")
) + ("pelvis",)
"""Joints a BVH file must provide; the others keep their parent's orientation when absent."""


@dataclass
class _BvhJoint:
    name: str
    parent: int
    offset: np.ndarray
    channels: list[str]
    end_site: np.ndarray | None = None


MAX_BVH_FRAMES = 100_000
"""Most frames :func:`load_bvh` reads: 55 minutes at 30 fps. The header's count sizes the frame array before the
frames are read, so a larger claim is refused (split longer captures into clips)."""


class _BvhReader:
    """Line-numbered tokens of a BVH file with errors that name the line."""

    def __init__(self, path: Path):
        self.path = path
        raw = path.read_bytes()
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as error:
            line = raw.count(b"\n", 0, error.start) + 1
            raise ValueError(
                f"{path}:{line}: not a text BVH file (byte {error.start} is not UTF-8); export the motion as BVH text"
            ) from None
        if "\x00" in text:
            line = text.count("\n", 0, text.index("\x00")) + 1
            raise ValueError(f"{path}:{line}: not a text BVH file (it holds NUL bytes); export the motion as BVH text")
        self.lines = [line.split() for line in text.splitlines()]
        self.line = 0

    def error(self, message: str, line: int | None = None) -> ValueError:
        return ValueError(f"{self.path}:{(self.line if line is None else line) + 1}: {message}")

    def next(self) -> list[str]:
        while self.line < len(self.lines) and not self.lines[self.line]:
            self.line += 1
        if self.line >= len(self.lines):
            raise self.error("unexpected end of file", len(self.lines) - 1)
        tokens = self.lines[self.line]
        self.line += 1
        return tokens

    def floats(self, tokens: list[str], count: int, what: str) -> np.ndarray:
        if len(tokens) != count:
            raise self.error(f"{what} needs {count} numbers, found {len(tokens)}", self.line - 1)
        try:
            values = np.array([float(x) for x in tokens])
        except ValueError:
            raise self.error(f"{what} holds a value that is not a number: {' '.join(tokens)}", self.line - 1) from None
        if not np.isfinite(values).all():
            shown = " ".join(t for t, v in zip(tokens, values, strict=True) if not np.isfinite(v))
            raise self.error(f"{what} holds a value that is not finite ({shown}); fix or drop the frame", self.line - 1)
        return values


def _parse_hierarchy(reader: _BvhReader) -> list[_BvhJoint]:
    if reader.next()[:1] != ["HIERARCHY"]:
        raise reader.error("a BVH file starts with HIERARCHY", reader.line - 1)
    joints: list[_BvhJoint] = []
    stack: list[int] = []
    tokens = reader.next()
    if tokens[:1] != ["ROOT"] or len(tokens) != 2:
        raise reader.error("expected 'ROOT <name>' after HIERARCHY", reader.line - 1)
    pending = ("joint", tokens[1])
    while True:
        kind, name = pending
        if reader.next() != ["{"]:
            raise reader.error(f"expected '{{' to open {name!r}", reader.line - 1)
        tokens = reader.next()
        if tokens[:1] != ["OFFSET"]:
            raise reader.error(f"expected OFFSET in {name!r}", reader.line - 1)
        offset = reader.floats(tokens[1:], 3, "OFFSET")
        if kind == "end":
            joints[stack[-1]].end_site = offset
            if reader.next() != ["}"]:
                raise reader.error("expected '}' to close End Site", reader.line - 1)
        else:
            tokens = reader.next()
            if tokens[:1] != ["CHANNELS"] or len(tokens) < 2 or not _is_count(tokens[1]):
                raise reader.error(f"expected 'CHANNELS <n> ...' in {name!r}", reader.line - 1)
            channels = tokens[2:]
            if len(channels) != int(tokens[1]) or any(c[1:] not in ("position", "rotation") for c in channels):
                raise reader.error(f"CHANNELS of {name!r} must list {tokens[1]} X/Y/Z position/rotation names")
            joints.append(_BvhJoint(name, stack[-1] if stack else -1, offset, channels))
            stack.append(len(joints) - 1)
        while True:
            tokens = reader.next()
            if tokens == ["}"]:
                stack.pop()
                if not stack:
                    return joints
                continue
            if tokens[:1] == ["JOINT"] and len(tokens) == 2:
                pending = ("joint", tokens[1])
            elif tokens[:2] == ["End", "Site"]:
                pending = ("end", "End Site")
            else:
                raise reader.error(f"expected JOINT, End Site or '}}', found {' '.join(tokens)!r}", reader.line - 1)
            break


def _parse_motion(reader: _BvhReader, channel_count: int) -> tuple[np.ndarray, float]:
    try:
        tokens = reader.next()
    except ValueError:
        raise reader.error("no MOTION section after the HIERARCHY", len(reader.lines) - 1) from None
    if tokens != ["MOTION"]:
        raise reader.error(f"expected MOTION after the HIERARCHY, found {' '.join(tokens)!r}", reader.line - 1)
    tokens = reader.next()
    if tokens[:1] != ["Frames:"] or len(tokens) != 2 or not _is_count(tokens[1]):
        raise reader.error("expected 'Frames: <count>'", reader.line - 1)
    count = int(tokens[1])
    if count > MAX_BVH_FRAMES:
        raise reader.error(
            f"'Frames: {count}' exceeds the {MAX_BVH_FRAMES} frames load_bvh reads (MAX_BVH_FRAMES); split the "
            "capture into shorter clips",
            reader.line - 1,
        )
    count_line = reader.line - 1
    tokens = reader.next()
    if tokens[:2] != ["Frame", "Time:"] or len(tokens) != 3:
        raise reader.error("expected 'Frame Time: <seconds>'", reader.line - 1)
    try:
        frame_time = float(tokens[2])
    except ValueError:
        raise reader.error(f"'Frame Time: {tokens[2]}' is not a number of seconds", reader.line - 1) from None
    if count < 1 or not 0 < frame_time < math.inf:
        raise reader.error("the motion needs at least one frame and a finite, positive frame time", reader.line - 1)
    if count > len(reader.lines) - reader.line:
        raise reader.error(
            f"'Frames: {count}' but only {len(reader.lines) - reader.line} lines follow; the file is truncated or "
            "the count is wrong",
            count_line,
        )
    values = np.empty((count, channel_count))
    for f in range(count):
        tokens = reader.next()
        if len(tokens) != channel_count:
            raise reader.error(
                f"frame {f} has {len(tokens)} values but the HIERARCHY declares {channel_count} channels",
                reader.line - 1,
            )
        values[f] = reader.floats(tokens, channel_count, f"frame {f}")
    return values, frame_time


def _is_count(token: str) -> bool:
    """Whether ``token`` is a non-negative decimal integer written in ASCII digits."""
    return token.isascii() and token.isdigit()


def _axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """[T, 3, 3] rotations about the x, y or z axis by ``angle`` [T] radians."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = {"X": (1, 2), "Y": (2, 0), "Z": (0, 1)}[axis]
    out = np.zeros((len(angle), 3, 3))
    out[:, 3 - i - j, 3 - i - j] = 1.0
    out[:, i, i], out[:, i, j], out[:, j, i], out[:, j, j] = c, -s, s, c
    return out


def _minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking direction ``a`` to direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    return axis_angle_to_matrix(torch.as_tensor(axis / max(np.linalg.norm(axis), 1e-300) * math.atan2(
        np.linalg.norm(axis), a @ b))).numpy()  # fmt: skip


def _resolve_names(
    joint_names: list[str], skeleton: Skeleton, name_map: dict[str, str] | None, path: Path
) -> dict[str, int]:
    """Our joint name → index of the BVH joint, checking that the required joints are present."""
    plain = {name.split(":")[-1].lower(): i for i, name in enumerate(joint_names)}
    if name_map is None:
        candidates = [{ours: BVH_NAME_MAPS[s].get(ours, ours) for ours in skeleton.names} for s in BVH_NAME_MAPS]
        name_map = max(candidates, key=lambda m: sum(v.lower() in plain for v in m.values()))
    found = {ours: plain[theirs.split(":")[-1].lower()] for ours, theirs in name_map.items()
             if theirs.split(":")[-1].lower() in plain}  # fmt: skip
    missing = [f"{ours} (as {name_map.get(ours, ours)!r})" for ours in REQUIRED_JOINTS if ours not in found]
    if missing:
        raise ValueError(
            f"{path}: no BVH joint for {', '.join(missing)}; the file's joints are {', '.join(joint_names)}. "
            "Pass name_map={our_joint: bvh_joint} for the joints named differently"
        )
    return found


def load_bvh(
    path: str | Path,
    skeleton: Skeleton,
    name_map: dict[str, str] | None = None,
    unit_scale: float | None = None,
    start_at_origin: bool = False,
) -> Motion:
    """Read a BVH motion file and retarget it onto ``skeleton``.

    Each joint's rotation is the product of its Euler channels in the order the CHANNELS line lists
    them (R = R_1 R_2 R_3). Retargeting transfers world bone orientations: our joint j, mapped to the
    file's joint a, gets W_j(t) = Q_a(t) C_j, where Q_a is the file's world rotation and C_j the minimal
    rotation from our rest bone direction to the file's rest bone direction (so the bones point the same
    way in every frame even when the rest poses differ, e.g. a T-pose file on our A-pose body). Joints
    that are not mapped keep their parent's orientation. The file is assumed y-up and facing +z; the
    root position channels give the root's world position.

    Args:
        path: the ``.bvh`` file.
        skeleton: the skeleton to retarget onto.
        name_map: our joint name → BVH joint name; ``None`` picks the best of :data:`BVH_NAME_MAPS`.
        unit_scale: metres per file unit; ``None`` uses the ratio of our leg length (hip to ankle) to
            the file's, which converts units and retargets the root motion to our body's size at once.
        start_at_origin: shift the root horizontally so that it starts above the origin.

    Returns:
        The retargeted motion at the file's frame rate.

    Raises:
        ValueError: a malformed file (the message names the file and line: binary content, a value that is not a
            finite number, more than :data:`MAX_BVH_FRAMES` frames) or a required joint that is missing.
    """
    path = Path(path)
    if unit_scale is not None and not (isinstance(unit_scale, (int, float)) and 0 < unit_scale < math.inf):
        raise ValueError(f"unit_scale must be a finite positive number of metres per file unit, got {unit_scale!r}")
    reader = _BvhReader(path)
    joints = _parse_hierarchy(reader)
    channel_count = sum(len(j.channels) for j in joints)
    values, frame_time = _parse_motion(reader, channel_count)
    frames = values.shape[0]
    found = _resolve_names([j.name for j in joints], skeleton, name_map, path)

    rest_pos = np.zeros((len(joints), 3))
    world_rot = np.zeros((frames, len(joints), 3, 3))
    root_pos = np.tile(joints[0].offset, (frames, 1))
    column = 0
    for i, joint in enumerate(joints):
        local = np.tile(np.eye(3), (frames, 1, 1))
        for name in joint.channels:
            if name.endswith("rotation"):
                local = local @ _axis_rotation(name[0], np.radians(values[:, column]))
            elif i == 0:
                root_pos[:, "XYZ".index(name[0])] = values[:, column]
            column += 1
        parent = joint.parent
        rest_pos[i] = joint.offset + (rest_pos[parent] if parent >= 0 else 0.0)
        world_rot[:, i] = local if parent < 0 else world_rot[:, parent] @ local

    ours_rest = skeleton.rest_positions.cpu().numpy().astype(np.float64)
    ours_tail = skeleton.rest_tails.cpu().numpy().astype(np.float64)
    if unit_scale is None:
        legs = [(found[f"{s}_hip"], found[f"{s}_knee"], found[f"{s}_ankle"]) for s in ("left", "right")]
        theirs = sum(np.linalg.norm(rest_pos[k] - rest_pos[h]) + np.linalg.norm(rest_pos[a] - rest_pos[k])
                     for h, k, a in legs)  # fmt: skip
        ours = sum(
            np.linalg.norm(ours_rest[skeleton.index(f"{s}_knee")] - ours_rest[skeleton.index(f"{s}_hip")])
            + np.linalg.norm(ours_rest[skeleton.index(f"{s}_ankle")] - ours_rest[skeleton.index(f"{s}_knee")])
            for s in ("left", "right")
        )
        if not theirs > 0:
            raise ValueError(
                f"{path}: the legs of its rest pose (OFFSETs from hip to ankle) have zero length, so its units "
                "cannot be found; pass unit_scale (metres per file unit)"
            )
        unit_scale = ours / theirs

    ours_world = np.zeros((frames, skeleton.num_joints, 3, 3))
    local = np.zeros_like(ours_world)
    for j, name in enumerate(skeleton.names):
        parent = skeleton.parents[j]
        if name not in found:
            ours_world[:, j] = ours_world[:, parent] if parent >= 0 else np.eye(3)
            local[:, j] = np.eye(3)
            continue
        correction = np.eye(3)
        child = next((k for k in range(skeleton.num_joints) if np.array_equal(ours_rest[k], ours_tail[j])), None)
        if child is not None and skeleton.names[child] in found:
            theirs_dir = rest_pos[found[skeleton.names[child]]] - rest_pos[found[name]]
            if np.linalg.norm(theirs_dir) > 0:
                correction = _minimal_rotation(ours_tail[j] - ours_rest[j], theirs_dir)
        ours_world[:, j] = world_rot[:, found[name]] @ correction
        local[:, j] = ours_world[:, j] if parent < 0 else ours_world[:, parent].transpose(0, 2, 1) @ ours_world[:, j]

    translation = unit_scale * root_pos - ours_rest[0]
    if start_at_origin:
        translation[:, [0, 2]] -= unit_scale * root_pos[0, [0, 2]]
    dtype = skeleton.rest_positions.dtype
    return Motion(
        torch.as_tensor(local, dtype=dtype),
        torch.as_tensor(translation, dtype=dtype),
        1.0 / frame_time,
        tuple(skeleton.names),
    )


def _matrix_to_euler_zxy(r: np.ndarray) -> np.ndarray:
    """Euler angles [..., 3] (z, x, y) in radians with R = R_z R_x R_y, for matrices [..., 3, 3]."""
    x = np.arcsin(np.clip(r[..., 2, 1], -1.0, 1.0))
    locked = np.abs(r[..., 2, 1]) > 1.0 - 1e-12
    z = np.where(locked, np.arctan2(r[..., 1, 0], r[..., 0, 0]), np.arctan2(-r[..., 0, 1], r[..., 1, 1]))
    y = np.where(locked, 0.0, np.arctan2(-r[..., 2, 0], r[..., 2, 2]))
    return np.stack([z, x, y], axis=-1)


def save_bvh(motion: Motion, path: str | Path, skeleton: Skeleton) -> None:
    """Write ``motion`` as a BVH file in centimetres with ZXY Euler channels in degrees.

    The hierarchy is ``skeleton`` at rest (end effectors get an End Site at their bone tail); the root
    has position channels holding its world position.
    """
    motion._check_skeleton(skeleton)
    cm = 100.0
    rest = skeleton.rest_positions.cpu().numpy().astype(np.float64)
    tails = skeleton.rest_tails.cpu().numpy().astype(np.float64)
    children = {j: [k for k, p in enumerate(skeleton.parents) if p == j] for j in range(skeleton.num_joints)}
    lines = ["HIERARCHY"]
    order = []

    def fmt(v):
        return " ".join(f"{x:.6f}" for x in v)

    def emit(j: int, depth: int):
        pad = "  " * depth
        parent = skeleton.parents[j]
        offset = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        lines.append(f"{pad}{'ROOT' if parent < 0 else 'JOINT'} {skeleton.names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {fmt(offset * cm)}")
        position = "Xposition Yposition Zposition " if parent < 0 else ""
        lines.append(f"{pad}  CHANNELS {6 if parent < 0 else 3} {position}Zrotation Xrotation Yrotation")
        order.append(j)
        for k in children[j]:
            emit(k, depth + 1)
        if not children[j]:
            lines.extend(
                [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {fmt((tails[j] - rest[j]) * cm)}", f"{pad}  }}"]
            )
        lines.append(f"{pad}}}")

    emit(0, 0)
    euler = np.degrees(_matrix_to_euler_zxy(motion.rotations.cpu().numpy().astype(np.float64)))[:, order]
    root = (motion.root_translation.cpu().numpy().astype(np.float64) + rest[0]) * cm
    lines += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {1.0 / motion.fps:.8f}"]
    for f in range(motion.num_frames):
        lines.append(fmt(np.concatenate([root[f], euler[f].ravel()])))
    Path(path).write_text("\n".join(lines) + "\n")


MOTIONS: dict[str, Callable[..., Motion]] = {"walk": walk, "turn": turn, "raise": raise_arms, "jump": jump}
"""The procedural motions by name."""


def named_motion(name: str, skeleton: Skeleton, steps: int, fps: float = 25.0) -> Motion:
    """The procedural motion ``name`` (a key of :data:`MOTIONS`) holding at least ``steps + 1`` poses.

    The clip keeps its own duration, and so its timing (e.g. the walk's one-second fade-in), when that already
    covers ``steps`` steps of ``1 / fps`` s; a longer request stretches it to exactly ``steps + 1`` poses.

    Raises:
        ValueError: an unknown name, or ``steps`` below 1.
    """
    if name not in MOTIONS:
        raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got {name!r}")
    if steps < 1:
        raise ValueError(f"a motion needs at least 1 step (2 poses), got {steps}")
    make = MOTIONS[name]
    clip = make(skeleton, fps=fps)
    return clip if clip.num_frames > steps else make(skeleton, duration=steps / fps, fps=fps)
