"""BVH motion files: read onto and written from the mannequin's skeleton (PhysAvatar §3.2 "Animation").

BVH files are read with per-joint Euler orders from their CHANNELS lines, retargeted onto our skeleton
by joint names (:data:`BVH_NAME_MAPS`) and by transferring each bone's world rotation; BVH files are
written with ZXY Euler channels in centimetres. Rotation conventions are those of :mod:`physavatar.body.skeleton`.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from physavatar.body.motion import Motion
from physavatar.body.skeleton import Skeleton, axis_angle_to_matrix

__all__ = [
    "BVH_NAME_MAPS",
    "MAX_BVH_FRAMES",
    "REQUIRED_JOINTS",
    "load_bvh",
    "save_bvh",
]

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
joints of a file is used, with the joints ``name_map`` names mapped as it says."""

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
    candidates = [{ours: BVH_NAME_MAPS[s].get(ours, ours) for ours in skeleton.names} for s in BVH_NAME_MAPS]
    name_map = {**max(candidates, key=lambda m: sum(v.lower() in plain for v in m.values())), **(name_map or {})}
    found = {ours: plain[theirs.split(":")[-1].lower()] for ours, theirs in name_map.items()
             if theirs.split(":")[-1].lower() in plain}  # fmt: skip
    missing = [f"{ours} (as {name_map.get(ours, ours)!r})" for ours in REQUIRED_JOINTS if ours not in found]
    if missing:
        raise ValueError(
            f"{path}: no BVH joint for {', '.join(missing)}; the file's joints are {', '.join(joint_names)}. "
            "Map the joints named differently, ours to the file's (load_bvh's name_map)"
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
        name_map: our joint name → BVH joint name, over the best-matching naming of :data:`BVH_NAME_MAPS` (which
            alone serves where ``None``).
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
    motion.check_skeleton(skeleton)
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
