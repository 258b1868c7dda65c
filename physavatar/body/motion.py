"""Procedural body motions that drive the garment (PhysAvatar §3.2 "Animation").

A :class:`Motion` is a sequence of poses of a :class:`~physavatar.body.Skeleton`: local joint
rotations and a root displacement per frame. The procedural clips (:func:`walk`, :func:`turn`,
:func:`raise_arms`, :func:`jump`) start exactly in the rest pose at rest (zero velocity), so a garment
draped on the rest body can start at frame 0 with zero velocity as the paper assumes, and their joint
angles are at least C1 in time (continuous angular velocities). Rotation conventions are those of
:mod:`physavatar.body.skeleton`: y up, facing +z, rotations in world axes at rest. BVH files are read
and written by :mod:`physavatar.body.bvh`.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from physavatar.body.skeleton import Skeleton, axis_angle_to_matrix

__all__ = [
    "MOTIONS",
    "Motion",
    "jump",
    "named_motion",
    "raise_arms",
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
        self.check_skeleton(skeleton)
        return skeleton.joint_positions(self.rotations, self.root_translation)

    def angular_speeds(self) -> torch.Tensor:
        """[T-1, J] angle of each joint's local rotation change between frames times fps, rad/s."""
        relative = self.rotations[:-1].transpose(-1, -2) @ self.rotations[1:]
        cos = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
        return torch.arccos(cos) * self.fps

    def check_skeleton(self, skeleton: Skeleton) -> None:
        """Refuse a skeleton whose joints are not the ones this motion poses (ValueError)."""
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
