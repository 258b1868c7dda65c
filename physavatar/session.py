"""An interactive garment session: the dressed mannequin moving through a motion, its garment dragged and pinned
with the mouse, its fabric changed and its contact watched (PhysAvatar §3.2 behind the interactive viewer's verbs).

:class:`AvatarSimulation` has the verbs of the PIE-NeRF bodies' :class:`pienerf.session.Simulation` that the viewer
(``python -m apps.demo --scene avatar``) calls — ``step``, ``pick``, ``drag_to``, ``grab``, ``release``,
``pin_picked``, ``reset``, ``deformed_mesh_vertices``, ``time_breakdown`` — and those of a moving body: ``play``,
``pause``, ``scrub``, ``set_speed``, ``set_motion``, and of a fabric: ``set_fabric``, ``apply_preset``
(:data:`FABRIC_PRESETS`). Each frame is one implicit step of :class:`~physavatar.cloth.SolverCloth` of ``Δt = 1 / 25``
s with the body moving between two poses of the motion and the waistband on its skinned targets (Eq. 5); the drag
and the pins are springs of the step's potential (:mod:`physavatar.cloth.picking`).

Garment size: on CUDA the DiffCloth skirt ``skirt7271`` of the shared data folder (3757 vertices) where present; on
the CPU the embedded procedural skirt at :data:`CPU_SKIRT` (6 rings of 16 vertices), which keeps a frame under 0.1 s
on two cores (figures in ``docs/benchmarks.md``, workload ``viewer_frame_avatar``). :attr:`AvatarSimulation.notes`
says which was chosen and why.

A user's capture (``docs/capture.md``; :attr:`AvatarConfig.capture`) replaces the mannequin and its motions: the
capture's body sequence is read by :func:`physavatar.capture.load_capture_folder` (its meshes only, no image) and
made simulable as the preparation stage makes it (:func:`physavatar.drive.drive_captured_garment`: the garment's
intersections resolved, the boundary given or chosen and carried by the body); it is resampled to 25 frames/s and
played forward then back, so that it loops without a jump.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.body import Body, Motion, jump, load_bvh, raise_arms, turn, walk
from physavatar.capture import load_capture_folder
from physavatar.cloth import ClothConfig, ClothControl, ClothStepReport, SolverCloth
from physavatar.cloth.picking import GarmentDrag, GarmentPick
from physavatar.drive import GAP_OVER_CONTACT_DISTANCE, drive_captured_garment
from physavatar.garment import (
    SHARED_GARMENTS,
    Garment,
    boundary_targets,
    load_garment,
    place_on_body,
    procedural_skirt,
    select_boundary,
)

__all__ = [
    "AVATAR_MOTIONS",
    "CAPTURE_MOTION",
    "CPU_SKIRT",
    "FABRIC_PRESETS",
    "AvatarConfig",
    "AvatarSimulation",
    "FabricPreset",
]

F64 = torch.float64
Progress = Callable[[str, float], None]
"""Progress callback: ``(stage, fraction in [0, 1])``."""

AVATAR_MOTIONS = ("walk", "turn", "raise", "jump")
"""The motions the session plays, each looping: ``walk`` walks in place (the root's forward travel taken out, so it
loops without a jump) and loops over two gait cycles after its fade-in; ``turn``, ``raise`` and ``jump`` end in the
pose they start in and loop whole."""

CAPTURE_MOTION = "capture"
"""The name of a capture's body sequence among the session's motions (its only one)."""

CPU_SKIRT = (6, 16)
"""``(rings, segments)`` of the procedural skirt the session wears on the CPU (96 vertices)."""

GARMENT_RGB = (0.80, 0.22, 0.20)
"""The garment's colour."""
CONTACT_RGB = (1.00, 0.85, 0.10)
"""The colour of garment vertices within the barrier's reach ``d̂`` of the body."""
BODY_RGB = (0.78, 0.74, 0.68)
"""The mannequin's colour."""

_FPS = 25.0  # frames per second of the motions; Δt = 1 / 25 s as the paper's 0.04 s
_WALK_PERIOD = 28  # frames of one gait cycle: cadence 25 / 28 cycles per second
_SCRUB_FRAMES_PER_STEP = 2.0  # a scrubbed body travels to its new pose this fast, so no step sweeps it far
_SPEED_RANGE = (0.0, 4.0)
_BVH_SECONDS = 20.0  # s of a BVH file played (its frames are skinned up front: 20 s of the mannequin is 90 MB)
_BVH_BLEND = 25  # frames of the eases into and out of a BVH clip (1 s)
_INTERACTIVE_NEWTON_ITERATIONS = {"cpu": 6, "cuda": 4}  # by device; see AvatarConfig.newton_iterations
_CPU_CANDIDATE_MARGIN = 0.01
"""m, the contact candidates' reach beyond each vertex's predicted path on the CPU (:attr:`ClothConfig.
candidate_margin`; the solver's 2 mm was the fastest for the converged walk): a dragged garment leaves a 2 mm reach
often, and each search costs a frame's tenth; at 1 cm the dragged skirt took 2.6 searches a frame instead of 5.8."""


@dataclass(frozen=True)
class FabricPreset:
    """A fabric: the simulator's material parameters (:class:`~physavatar.cloth.ClothConfig`).

    Attributes:
        density: volumetric density ``ρ``, kg/m³ (areal density ``ρ h``).
        kappa_s: membrane stiffness multiplier ``κ_s`` (``E = κ_s · 0.821 MPa``).
        kappa_b: bending stiffness multiplier ``κ_b``.
        friction: friction coefficient ``μ`` against the body and itself.
        thickness: sheet thickness ``h``, m (bending grows as ``h³``).
    """

    density: float
    kappa_s: float
    kappa_b: float
    friction: float
    thickness: float = 0.318e-3


FABRIC_PRESETS: dict[str, FabricPreset] = {
    "silk": FabricPreset(density=200.0, kappa_s=0.3, kappa_b=0.1, friction=0.1),
    "cotton": FabricPreset(density=472.641509, kappa_s=1.0, kappa_b=1.0, friction=0.2),
    "denim": FabricPreset(density=640.0, kappa_s=4.0, kappa_b=8.0, friction=0.4),
    "leather": FabricPreset(density=640.0, kappa_s=8.0, kappa_b=8.0, friction=0.5, thickness=0.9e-3),
}
"""Fabric presets, within PhysAvatar's ranges (ρ 200–640 kg/m³, κ 0.1–8, Appendix A.3):

- ``silk``: 64 g/m² (ρ 200 at h = 0.318 mm), soft in stretch (κ_s 0.3) and bending (κ_b 0.1), slippery (μ 0.1);
- ``cotton``: C-IPC's isotropic cotton, the simulator's default: 150 g/m², κ_s = κ_b = 1, μ 0.2;
- ``denim``: 204 g/m², four times cotton's stretch stiffness and eight times its bending, μ 0.4;
- ``leather``: 0.9 mm thick, 576 g/m², κ_s = κ_b = 8, so its bending is 8 · (0.9 / 0.318)³ ≈ 180 times cotton's;
  μ 0.5."""

_RANGES = {
    "density": (200.0, 640.0),
    "kappa_s": (0.1, 8.0),
    "kappa_b": (0.1, 8.0),
    "friction": (0.0, 1.0),
}


def _check_motion(name) -> None:
    """Refuse a motion that is neither one of :data:`AVATAR_MOTIONS` nor a ``.bvh`` file."""
    if name in AVATAR_MOTIONS:
        return
    if not (isinstance(name, str) and name.lower().endswith(".bvh") and Path(name).is_file()):
        raise ValueError(f"unknown motion {str(name)[:80]!r}; valid: {', '.join(AVATAR_MOTIONS)} or a .bvh file")


def _number(value, name: str) -> float:
    lo, hi = _RANGES[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"{name.replace('_', ' ')} must be a number in [{lo:g}, {hi:g}], got {str(value)[:80]}")
    return float(value)


@dataclass(frozen=True)
class AvatarConfig:
    """Settings of an :class:`AvatarSimulation`.

    Attributes:
        capture: a user's capture folder (``docs/capture.md``) whose body sequence the garment is simulated on, in
            place of the mannequin and its motions (``motion`` is then ignored); ``None``: the mannequin.
        garment: with ``capture``: ``None`` for the capture's garment, or the path of an OBJ/PLY garment worn by
            the capture's body at its first frame, in the capture's axes and metres. Otherwise ``None`` picks by
            device (``skirt7271`` of the shared data on CUDA where present, else the
            procedural skirt at :data:`CPU_SKIRT`); ``"procedural"``; a shared garment's name (``"skirt1252"``,
            ``"skirt7271"``, :data:`physavatar.garment.SHARED_GARMENTS`); or the path of an OBJ/PLY garment.
        skirt: ``(rings, segments)`` of the procedural skirt.
        motion: the motion at start: one of :data:`AVATAR_MOTIONS` or the path of a ``.bvh`` file (retargeted onto
            the mannequin, eased in from the rest pose and back to its first pose so that it loops).
        fabric: the fabric at start (:data:`FABRIC_PRESETS`).
        newton_iterations: most Newton iterations a frame; ``None``: an interactive cap, as the PIE-NeRF bodies'
            one iteration: 6 on the CPU, 4 on CUDA. With the garment dragged across the walking legs a converged
            frame took 22 iterations on average on the CPU, a capped one 6, a quarter of the time; walking alone,
            skirt7271 takes 5 a frame (``cloth_step``), so the cap binds while the user drags. Every iterate is
            intersection-free, so a capped step keeps the contact guarantees; it may end with the body short of its
            pose, and then the body is shown where the garment's collider got to and the next step sweeps on from
            there (:attr:`AvatarSimulation.body_lag`). The solver's own 50 converges every frame. On an H200,
            skirt7271 dragged on the walk (the ``viewer_frame_avatar`` frame, 40 frames after 10): a cap of 6 took
            49.0 ms a frame (median; 5.8 iterations), 5 took 42.9 ms, 4 took 38.4 ms (26 frames/s), with the body
            at most 2.9 mm behind its pose and no vertex inside it; the linear solves (cuDSS) are half the frame.
        collider_reach: the garment collides with the body's triangles that have a vertex within this distance
            of the garment at rest, m; ``None``: 0.25 m on the CPU (the hips, thighs and hands that a skirt meets:
            the candidate search, most of a frame there, sees 6k of the body's 15k triangles), the whole body on
            CUDA. The contact view's counter of vertices inside the body always tests the whole body.
        drag_stiffness: drag spring ``k``, N/m; ``None`` → 20 × the garment's weight per metre (a stiffer spring
            on one vertex pulls a sharper tent into the cloth, which takes Newton more iterations).
        drag_damping: drag damper ``c`` as a time, s (``c = k × drag_damping``).
        drag_max_force: largest drag force, in garment weights.
        pin_stiffness: a pin's spring, in drag stiffnesses.
        speed: motion frames per step at start (1: real time).
    """

    garment: str | None = None
    capture: str | None = None
    skirt: tuple[int, int] = CPU_SKIRT
    motion: str = "walk"
    fabric: str = "cotton"
    newton_iterations: int | None = None
    collider_reach: float | None = None
    drag_stiffness: float | None = None
    drag_damping: float = 0.02
    drag_max_force: float = 20.0
    pin_stiffness: float = 20.0
    speed: float = 1.0

    def __post_init__(self):
        _check_motion(self.motion)
        if self.capture is not None:
            if not Path(self.capture).is_dir():
                raise ValueError(
                    f"capture {str(self.capture)[:200]!r} is not a folder; pass a capture folder (docs/capture.md)"
                )
            if self.garment is not None and not Path(self.garment).is_file():
                raise ValueError(
                    f"with a capture the garment must be an OBJ/PLY file worn by the capture's body at its first "
                    f"frame, got {self.garment!r}; leave it out to wear the capture's own garment"
                )
        if self.fabric not in FABRIC_PRESETS:
            raise ValueError(f"unknown fabric {self.fabric!r}; valid: {', '.join(FABRIC_PRESETS)}")
        if self.newton_iterations is not None and not (
            isinstance(self.newton_iterations, int) and self.newton_iterations >= 1
        ):
            raise ValueError(f"newton_iterations must be an integer >= 1 (or None), got {self.newton_iterations!r}")
        if self.drag_stiffness is not None and not 0.0 < self.drag_stiffness < math.inf:
            raise ValueError(f"drag_stiffness must be a finite number > 0 N/m (or None), got {self.drag_stiffness!r}")
        for name in ("drag_max_force", "pin_stiffness"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be a finite number > 0, got {getattr(self, name)!r}")
        if self.collider_reach is not None and not 0.0 < self.collider_reach:
            raise ValueError(f"collider_reach must be a distance > 0 m (or None), got {self.collider_reach!r}")
        if not 0.0 <= self.drag_damping < math.inf:
            raise ValueError(f"drag_damping must be a finite number >= 0 s, got {self.drag_damping!r}")
        if not _SPEED_RANGE[0] <= self.speed <= _SPEED_RANGE[1]:
            raise ValueError(f"speed must lie in {_SPEED_RANGE[0]:g}..{_SPEED_RANGE[1]:g} frames a step")


@dataclass(frozen=True)
class _Clip:
    """A motion as the session plays it: the body and the waistband per frame, and where it loops back to."""

    body: torch.Tensor  # [T, B, 3] body vertices per frame (m), on the device
    collider: torch.Tensor  # [T, C, 3] the garment's collider: the body vertices it keeps, per frame (m)
    targets: torch.Tensor  # [T, D, 3] boundary targets per frame (m), on the device
    loop_start: int  # the frame whose pose equals the last frame's: playing on from the end continues there

    @property
    def last(self) -> int:
        return self.body.shape[0] - 1

    def at(self, frame: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Body ``[B, 3]``, collider ``[C, 3]`` and targets ``[D, 3]`` at a fractional frame in ``[0, last]``
        (linear in between)."""
        i = min(int(math.floor(frame)), self.last - 1)
        f = frame - i
        return tuple(torch.lerp(a[i], a[i + 1], f) for a in (self.body, self.collider, self.targets))

    def advance(self, frame: float, frames: float) -> float:
        """``frame`` moved on by ``frames``, looping from the last frame to :attr:`loop_start`."""
        frame += frames
        span = self.last - self.loop_start
        while frame > self.last:
            frame -= span
        return frame


def _bvh_motion(path: Path, body: Body) -> tuple[Motion, int, str]:
    """A BVH file as a looping clip at 25 fps: ``(motion, loop start, note)``.

    The file is retargeted onto the mannequin (:func:`physavatar.body.load_bvh`, its root starting above the origin),
    sampled at 25 fps (the nearest frame) and cut at :data:`_BVH_SECONDS`; the clip eases from the rest pose (the pose
    the garment was placed in) to the file's first pose over :data:`_BVH_BLEND` frames, and from its last pose back to
    its first over as many, so that it loops without a jump; the loop starts at the file's first pose."""
    motion = load_bvh(path, body.skeleton, start_at_origin=True)
    pick = torch.arange(0.0, motion.num_frames - 1 + 1e-9, motion.fps / _FPS).round().long()
    cut = pick[: int(_BVH_SECONDS * _FPS) + 1]
    rotations, root = motion.rotations[cut], motion.root_translation[cut]
    rest_rotations = torch.eye(3, dtype=rotations.dtype).expand_as(rotations[0])
    ease = torch.tensor([_ease_weight(k / _BVH_BLEND) for k in range(_BVH_BLEND)], dtype=rotations.dtype)

    def blend(a_rot, a_root, b_rot, b_root):
        # rotation matrices blended entry-wise and re-orthonormalised (SVD): the poses are a second apart at most
        mixed = torch.lerp(a_rot[None], b_rot[None], ease[:, None, None, None])
        u, _, v = torch.linalg.svd(mixed)
        return u @ v, torch.lerp(a_root[None], b_root[None], ease[:, None])

    into = blend(rest_rotations, torch.zeros_like(root[0]), rotations[0], root[0])
    back = blend(rotations[-1], root[-1], rotations[0], root[0])
    clip = Motion(
        torch.cat([into[0], rotations, back[0][1:], rotations[:1]]),
        torch.cat([into[1], root, back[1][1:], root[:1]]),
        _FPS,
        motion.joint_names,
    )
    seconds = cut.numel() / _FPS
    note = f"{path.name}: {seconds:.1f} s at 25 fps" + (" (cut)" if pick.numel() > cut.numel() else "")
    return clip, _BVH_BLEND, note


def _resample(frames: torch.Tensor, fps: float) -> torch.Tensor:
    """``[T, N, 3]`` frames at ``fps`` resampled to the session's 25 frames/s, linearly between two frames: ``[K + 1,
    N, 3]``, ``K = ⌈(T − 1) · 25 / fps⌉``, the last one the sequence's last frame."""
    last = frames.shape[0] - 1
    count = max(1, math.ceil(last * _FPS / fps - 1e-9))
    at = torch.clamp(torch.arange(count + 1, dtype=torch.float64) * (fps / _FPS), max=float(last))
    lo = torch.clamp(at.floor().long(), max=max(last - 1, 0))
    weight = (at - lo).to(frames.dtype)[:, None, None]
    return torch.lerp(frames[lo], frames[torch.clamp(lo + 1, max=last)], weight)


def _ease_weight(t: float) -> float:
    """Smoothstep ``3t² − 2t³``: 0 at 0, 1 at 1, still at both ends."""
    return t * t * (3.0 - 2.0 * t)


def _motion(name: str, body: Body) -> tuple[Motion, int]:
    """The motion ``name`` and its loop start (:data:`AVATAR_MOTIONS`)."""
    skeleton = body.skeleton
    if name == "walk":
        # three gait cycles of 28 frames: the fade-in ends within the first, the last two loop
        motion = walk(skeleton, duration=3 * _WALK_PERIOD / _FPS, fps=_FPS, cadence=_FPS / _WALK_PERIOD)
        root = motion.root_translation.clone()
        root[:, [0, 2]] = 0.0  # in place
        return Motion(motion.rotations, root, motion.fps, motion.joint_names), _WALK_PERIOD
    make = {"turn": turn, "raise": raise_arms, "jump": jump}[name]
    return make(skeleton, fps=_FPS), 0


def _load_garment(choice: str | None, body: Body, skirt: tuple[int, int], device: torch.device) -> tuple[Garment, str]:
    """The garment and a sentence saying which it is and why."""
    shared = SHARED_GARMENTS / "skirt7271.obj"
    if choice is None:
        if device.type == "cuda" and shared.is_file():
            return place_on_body(load_garment(shared), body), "the full skirt7271 (3757 vertices) on CUDA"
        rings, segments = skirt
        why = "on the CPU, to stay interactive" if device.type == "cpu" else f"{shared} is absent"
        return (
            place_on_body(procedural_skirt(body, rings=rings, segments=segments), body),
            f"the procedural skirt of {rings * segments} vertices ({rings} rings of {segments}) {why}; "
            "choose another with --garment",
        )
    if choice == "procedural":
        rings, segments = skirt
        return place_on_body(procedural_skirt(body, rings=rings, segments=segments), body), (
            f"the procedural skirt of {rings * segments} vertices"
        )
    path = Path(choice)
    if not path.is_file() and (SHARED_GARMENTS / f"{choice}.obj").is_file():
        path = SHARED_GARMENTS / f"{choice}.obj"
    if not path.is_file():
        raise FileNotFoundError(
            f"garment {choice!r} is neither a file nor a shared garment ({SHARED_GARMENTS}); pass an OBJ/PLY path, "
            "'procedural' or a shared garment's name such as skirt7271"
        )
    garment = place_on_body(load_garment(path), body)
    return garment, f"{path.name} ({garment.vertices.shape[0]} vertices)"


class AvatarSimulation:
    """The dressed mannequin in motion, with the user's drag, pins, fabric and playback.

    Args:
        config: the session's settings.
        progress: called with ``(stage, fraction)`` while the scene is built.

    Attributes:
        kind: ``"garment"``: viewers show the garment panel for it.
        notes: sentences on what was chosen (the garment and why).
        last_report: the last step's :class:`~physavatar.cloth.ClothStepReport`.
        body_lag: how far (m) the garment's collider ended the last step short of its pose (0 when the step
            converged; see :attr:`AvatarConfig.newton_iterations`).
        motions, fabric_presets: the names :meth:`set_motion` and :meth:`apply_preset` take, for menus.
    """

    kind = "garment"
    fabric_presets = tuple(FABRIC_PRESETS)

    def __init__(self, config: AvatarConfig = AvatarConfig(), progress: Progress | None = None):
        self.config = config
        device = backend.torch_device()
        self._clips: dict[str, _Clip] = {}
        if config.capture is not None:
            self.body = None
            body_vertices, body_faces, garment, self.boundary = self._captured(config, progress)
        else:
            self._progress(progress, "building the mannequin", 0.0)
            self.body = Body.mannequin(spacing=0.03)
            body_vertices, body_faces = self.body.vertices, self.body.faces
            self._progress(progress, "placing the garment", 0.3)
            garment, note = _load_garment(config.garment, self.body, config.skirt, device)
            self.notes = (f"wearing {note}", *garment.notes)
            self.boundary = select_boundary(garment, self.body, mode="auto")
        self.body_faces = body_faces.to(torch.int32)
        self.garment = garment
        self._boundary = self.boundary.long().to(device)
        self.mesh_vertices = garment.vertices.float()
        self.mesh_faces = garment.faces.to(torch.int32)
        lo, hi = body_vertices.amin(0), body_vertices.amax(0)
        self.centre = (0.5 * (lo + hi)).float()
        self.centre[1] = float(garment.vertices[:, 1].mean())
        reach = config.collider_reach
        if reach is None:
            reach = 0.25 if device.type == "cpu" else math.inf
        near = torch.cdist(body_vertices.float(), garment.vertices.float()).min(1).values < reach
        faces = body_faces[near[body_faces].any(1)]
        self.collider_vertices = torch.unique(faces)  # [C] body vertices the garment's collider keeps
        remap = torch.full((body_vertices.shape[0],), -1, dtype=torch.int64)
        remap[self.collider_vertices] = torch.arange(self.collider_vertices.numel())
        self.collider_faces = remap[faces]
        self._collider_index = self.collider_vertices.to(device)
        if math.isfinite(reach):
            self.notes = (
                *self.notes,
                f"the garment collides with the {faces.shape[0]} of the body's {body_faces.shape[0]} triangles "
                f"within {reach:g} m of it",
            )
        self._progress(progress, "skinning the motion", 0.5)
        self.motion = CAPTURE_MOTION if config.capture is not None else config.motion
        self._clip_of(self.motion)
        self.solver_device = device
        self.newton_iterations = config.newton_iterations or _INTERACTIVE_NEWTON_ITERATIONS[device.type]
        self.fabric_name = config.fabric
        self.fabric = FABRIC_PRESETS[config.fabric]
        self._progress(progress, "building the solver", 0.7)
        self._make_solver()
        weight = float(self.solver.potential.mass.sum()) * 9.81
        stiffness = config.drag_stiffness or 20.0 * weight
        self.drag = GarmentDrag(
            self.mesh_faces,
            stiffness=stiffness,
            damping=config.drag_damping * stiffness,
            max_force=config.drag_max_force * weight,
            pin_stiffness=config.pin_stiffness * stiffness,
        )
        self.particle_radius = 0.5 * float(
            (garment.vertices[garment.faces[:, 0]] - garment.vertices[garment.faces[:, 1]]).norm(dim=1).mean()
        )
        self.particle_colors = torch.tensor(GARMENT_RGB).expand(garment.vertices.shape[0], 3).clone()
        self.render_backends: dict = {}
        self.speed = config.speed
        self.playing = True
        self._contact_bvh: MeshBVH | None = None
        self._progress(progress, "ready", 1.0)
        self.reset()

    @staticmethod
    def _progress(progress: Progress | None, stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    def _captured(self, config: AvatarConfig, progress: Progress | None):
        """The capture's body ``[B, 3]`` at frame 0 and faces ``[G, 3]``, the garment and its boundary ``[D]``;
        the body sequence's clip waits in :attr:`_capture_clip` for :meth:`_clip_of`."""
        self._progress(progress, f"reading the capture {Path(config.capture).name}", 0.0)
        try:
            folder = load_capture_folder(config.capture, views=False)
        except (FileNotFoundError, ValueError) as error:
            raise ValueError(
                f"{config.capture} is not a capture this viewer can play: {error} (the format: docs/capture.md; "
                f"python -m apps.avatar check {config.capture} lists every problem)"
            ) from None
        garment_vertices, garment_faces, boundary = folder.garment_vertices, folder.garment_faces, folder.boundary
        name, worn = folder.path.name, f"the capture's garment ({garment_vertices.shape[0]} vertices)"
        if config.garment is not None:
            given = load_garment(config.garment, scale=None)
            garment_vertices, garment_faces, boundary = folder.from_capture_axes(given.vertices), given.faces, None
            name, worn = Path(config.garment).stem, f"{Path(config.garment).name} ({given.vertices.shape[0]} vertices)"
        self._progress(progress, "resolving the garment's intersections", 0.3)
        gap = GAP_OVER_CONTACT_DISTANCE * ClothConfig().contact_distance
        captured = drive_captured_garment(
            folder.body_frames, folder.body_faces, garment_vertices, garment_faces, boundary, folder.fps, gap, name
        )
        driver = captured.driver
        frames = _resample(driver.body_frames, folder.fps)
        targets = _resample(driver.boundary_targets, folder.fps)
        # forward then back: the last frame is the first's pose, so the loop goes on from frame 0 without a jump
        self._capture_clip = tuple(torch.cat([a, a.flip(0)[1:]]) for a in (frames, targets))
        self.notes = (
            f"wearing {worn} on the body of the capture {folder.path.name}: {driver.frames} frames at "
            f"{folder.fps:g} fps, played at 25 fps forward then back",
            f"{captured.intersections.summary()}; {driver.boundary_index.numel()} boundary vertices "
            f"({captured.boundary_chosen})",
        )
        return folder.body_frames[0], folder.body_faces, captured.garment, driver.boundary_index

    def _clip_of(self, name: str) -> _Clip:
        if name not in self._clips and self.body is None:
            if name != CAPTURE_MOTION:
                raise ValueError(f"unknown motion {str(name)[:80]!r}; a capture plays its own: {CAPTURE_MOTION}")
            device = backend.torch_device()
            body, targets = (a.to(device, F64) for a in self._capture_clip)
            self._clips[name] = _Clip(body, body[:, self.collider_vertices.to(device)].contiguous(), targets, 0)
        if name not in self._clips:
            if name in AVATAR_MOTIONS:
                motion, loop_start = _motion(name, self.body)
            else:
                motion, loop_start, note = _bvh_motion(Path(name), self.body)
                self.notes = (*self.notes, f"playing {note}")
            device = backend.torch_device()
            index = self.boundary.long()
            body = self.body.skin(motion.rotations, motion.root_translation).to(device, F64)
            self._clips[name] = _Clip(
                body,
                body[:, self.collider_vertices.to(device)].contiguous(),
                boundary_targets(self.body, self.garment.vertices[index], motion.rotations, motion.root_translation).to(
                    device, F64
                ),
                loop_start,
            )
        return self._clips[name]

    def _cloth_config(self) -> ClothConfig:
        f = self.fabric
        return ClothConfig(
            density=f.density,
            kappa_s=f.kappa_s,
            kappa_b=f.kappa_b,
            friction=f.friction,
            thickness=f.thickness,
            max_newton_iterations=self.newton_iterations,
            candidate_margin=_CPU_CANDIDATE_MARGIN if self.solver_device.type == "cpu" else None,
        )

    def _make_solver(self) -> None:
        self.solver = SolverCloth(self.garment.vertices, self.garment.faces, self._cloth_config(), self.collider_faces)
        self.dt = 1.0 / _FPS

    # -- state and stepping ------------------------------------------------------------------------------

    @property
    def motions(self) -> tuple[str, ...]:
        """The motions :meth:`set_motion` takes: :data:`AVATAR_MOTIONS` and the BVH files played so far, or a
        capture's body sequence alone (:data:`CAPTURE_MOTION`)."""
        if self.body is None:
            return (CAPTURE_MOTION,)
        return (*AVATAR_MOTIONS, *(name for name in self._clips if name not in AVATAR_MOTIONS))

    @property
    def clip(self) -> _Clip:
        """The motion being played."""
        return self._clip_of(self.motion)

    @property
    def frame_count(self) -> int:
        """Frames of the motion (the scrub range is ``0 … frame_count − 1``)."""
        return self.clip.last + 1

    def reset(self) -> None:
        """Back to the rest pose at the motion's first frame, the garment at rest; drag and pins cleared."""
        self.state = self.solver.initial_state()
        self._spare = self.solver.initial_state()
        self.frame = 0.0
        self._goal: float | None = None
        self.time = 0.0
        self.drag.clear()
        self.last_report = ClothStepReport(0, True, math.inf, math.inf, 0)
        self._phases = {"candidate search": 0.0, "Newton iterations": 0.0, "linear solves": 0.0, "contact view": 0.0}
        self._steps = 0
        self.body_now, self._collider_now, _ = self.clip.at(0.0)
        self.body_lag = 0.0  # m, how far the body's pose is behind the motion's (see step)
        self._update_contact()

    def step(self, count: int = 1) -> ClothStepReport:
        """Advance ``count`` frames of ``Δt = 1/25`` s: the body moves on by :attr:`speed` frames of its motion
        while playing (or toward a scrubbed frame), the garment follows in one implicit step."""
        for _ in range(count):
            clip = self.clip
            start = self.frame
            if self._goal is not None:
                gap = self._goal - start
                wrapped = start + max(-_SCRUB_FRAMES_PER_STEP, min(_SCRUB_FRAMES_PER_STEP, gap))
                if wrapped == self._goal:
                    self._goal = None
            elif self.playing and self.speed > 0.0:
                wrapped = clip.advance(start, self.speed)
            else:
                wrapped = start
            # from the last step's body (the last frame's pose is the loop start's, so a wrap moves it a frame)
            body_end, collider_end, targets = clip.at(wrapped)
            control = ClothControl(self._collider_now, collider_end, self._boundary, targets)
            springs = self.drag.springs(self.state.x, self.dt)
            if springs is not None:
                control.spring_index, control.spring_target, control.spring_stiffness = springs
            report = self.solver.step(self.state, self._spare, control, self.dt)
            self.state, self._spare = self._spare, self.state
            # where the body got to: under the Newton cap a step may end before the kinematic body reaches its
            # pose (every iterate is intersection-free, the pose is not forced), and the next step sweeps on from
            # there, so the body lags a little instead of jumping through the garment
            reached = self.solver.loop.positions()[self.solver.vertex_count :]
            self.body_lag = float((reached - collider_end).abs().max())
            self._collider_now = reached.clone()
            # the body as the garment saw it: the pose, with the collider where the step left it
            body_end = body_end.clone()
            body_end[self._collider_index] = reached
            self.frame, self.body_now, self.time = wrapped, body_end, self.time + self.dt
            self.last_report = report
            self._account(report)
            self._update_contact()
        return self.last_report

    def _account(self, report: ClothStepReport) -> None:
        t = report.time
        self._steps += 1
        self._phases["candidate search"] += t.get("broad_phase", 0.0)
        self._phases["Newton iterations"] += sum(t.get(k, 0.0) for k in ("assemble", "ccd", "line_search", "friction"))
        self._phases["linear solves"] += t.get("solve", 0.0)

    def _update_contact(self) -> None:
        """The garment's distance to the body now: tint, minimum, vertices inside (:meth:`contact`)."""
        clock = time.perf_counter()
        body = self.body_now.to(torch.float32)
        if self._contact_bvh is None:
            self._contact_bvh = MeshBVH(body, self.body_faces.to(body.device), winding_numbers=True)
        else:
            self._contact_bvh.refit(body)
        reach = self.solver.config.contact_distance
        x = self.state.x.to(torch.float32)
        nearest = self._contact_bvh.closest(x, max_distance=100.0 * reach)
        inside = self._contact_bvh.inside(x)
        self._near = (nearest.distance < reach).cpu()
        self._min_body = float(nearest.distance.min())
        self._inside = int(inside.sum())
        backend.synchronize()
        if self._steps:
            self._phases["contact view"] += time.perf_counter() - clock

    def contact(self) -> dict:
        """The garment's contact now: ``near`` (vertices within ``d̂`` of the body), ``min_body_m`` (the smallest
        vertex–body distance, ``inf`` beyond 100 ``d̂``), ``min_self_m`` (the step's smallest garment–garment
        distance, ``inf`` beyond ``d̂``), ``inside`` (vertices inside the body: 0 by the barrier's guarantee) and
        ``reach_m`` (``d̂``)."""
        return {
            "near": int(self._near.sum()),
            "min_body_m": self._min_body,
            "min_self_m": self.last_report.min_distance_self,
            "inside": self._inside,
            "reach_m": self.solver.config.contact_distance,
        }

    def max_speed(self) -> float:
        """How fast things move (m/s): ``inf`` while the body plays or travels to a scrubbed frame, else the
        garment's largest vertex speed."""
        if (self.playing and self.speed > 0.0) or self._goal is not None or self.dragging:
            return math.inf
        return float(self.state.v.norm(dim=1).max())

    # -- playback ------------------------------------------------------------------------------------------

    def play(self) -> None:
        """Play the motion (the garment simulates whether it plays or not)."""
        self.playing = True

    def pause(self) -> None:
        """Hold the body in its pose; the garment keeps simulating (drag it, let it settle)."""
        self.playing = False

    def scrub(self, frame: float) -> float:
        """Move the body to ``frame`` of its motion (``0 … frame_count − 1``), travelling there at
        :data:`_SCRUB_FRAMES_PER_STEP` frames a step so that no step sweeps it far; returns the frame."""
        last = self.clip.last
        if isinstance(frame, bool) or not isinstance(frame, (int, float)) or not 0 <= frame <= last:
            raise ValueError(f"frame must be a number in [0, {last}] (the motion's frames), got {str(frame)[:80]}")
        self._goal = float(frame)
        return self._goal

    def set_speed(self, speed: float) -> float:
        """Motion frames per step: 1 plays in real time, 0 holds the pose."""
        lo, hi = _SPEED_RANGE
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not lo <= speed <= hi:
            raise ValueError(f"speed must be a number in [{lo:g}, {hi:g}] (motion frames a step), got {speed!r}")
        self.speed = float(speed)
        return self.speed

    def set_motion(self, name: str) -> None:
        """Play motion ``name`` (:data:`AVATAR_MOTIONS`) from its first frame: the body and the garment start again
        from rest (the first pose of every motion is the rest pose), pins and drag cleared."""
        if self.body is None:
            if name != CAPTURE_MOTION:
                raise ValueError(f"unknown motion {str(name)[:80]!r}; a capture plays its own: {CAPTURE_MOTION}")
        else:
            _check_motion(name)
        self.motion = name
        self._clip_of(name)
        self.reset()

    # -- fabric --------------------------------------------------------------------------------------------

    def set_fabric(self, density=None, kappa_s=None, kappa_b=None, friction=None) -> FabricPreset:
        """Change the fabric: density ``ρ`` (kg/m³), ``κ_s``, ``κ_b`` and friction ``μ`` (PhysAvatar's ranges). The
        solver is built anew with them; the garment keeps its state, pins and drag."""
        changes = {
            name: _number(value, name)
            for name, value in (
                ("density", density),
                ("kappa_s", kappa_s),
                ("kappa_b", kappa_b),
                ("friction", friction),
            )
            if value is not None
        }
        return self._use_fabric(replace(self.fabric, **changes), "custom" if changes else self.fabric_name)

    def apply_preset(self, name: str) -> FabricPreset:
        """Use fabric ``name`` of :data:`FABRIC_PRESETS`."""
        if name not in FABRIC_PRESETS:
            raise ValueError(f"unknown fabric {str(name)[:40]!r}; valid: {', '.join(FABRIC_PRESETS)}")
        return self._use_fabric(FABRIC_PRESETS[name], name)

    def _use_fabric(self, fabric: FabricPreset, name: str) -> FabricPreset:
        state = self.state
        self.fabric, self.fabric_name = fabric, name
        self._make_solver()
        # the new solver's states: the step writes into tensors of its own making
        self.state, self._spare = self.solver.initial_state(), self.solver.initial_state()
        self.state.x.copy_(state.x)
        self.state.v.copy_(state.v)
        return fabric

    # -- interaction ---------------------------------------------------------------------------------------

    def pick(self, ray_origin, ray_direction) -> GarmentPick | None:
        """Pick the garment under a ray (m, scene axes); starts a drag."""
        return self.drag.pick(ray_origin, ray_direction, self.state.x)

    def drag_to(self, ray_origin=None, ray_direction=None, *, target=None) -> torch.Tensor:
        """Move the drag target along a new ray at the picked depth, or to ``target`` (m)."""
        return self.drag.update(ray_origin, ray_direction, target=target)

    def grab(self, vertex: int) -> GarmentPick:
        """Start a drag at garment vertex ``vertex``, as a scripted mouse does."""
        return self.drag.grab(vertex, self.state.x)

    def release(self) -> None:
        """Let go of the dragged vertex."""
        self.drag.release()

    @property
    def dragging(self) -> bool:
        """Whether a vertex is dragged."""
        return self.drag.dragging

    @property
    def drag_target(self) -> torch.Tensor | None:
        """``[3]`` where the drag pulls (m), or ``None``."""
        return self.drag.target if self.dragging else None

    def pin_picked(self) -> int:
        """Pin the picked vertex where it is now; returns the vertex."""
        return self.drag.pin_picked(self.state.x)

    # -- output --------------------------------------------------------------------------------------------

    def deformed_mesh_vertices(self) -> torch.Tensor:
        """``[V, 3]`` float32 garment vertices now (m), a CPU tensor the caller owns."""
        return self.state.x.to("cpu", torch.float32)

    def particle_positions(self) -> torch.Tensor:
        """``[V, 3]`` the garment's vertices (m), the particle view's points."""
        return self.deformed_mesh_vertices()

    def body_vertices(self) -> torch.Tensor:
        """``[B, 3]`` float32 mannequin vertices now (m), on the CPU."""
        return self.body_now.to("cpu", torch.float32)

    def near_body(self) -> torch.Tensor:
        """``[V]`` bool, on the CPU: the garment vertices within the barrier's reach ``d̂`` of the body now (the
        tinted ones of :meth:`vertex_colors`)."""
        return self._near.clone()

    def vertex_colors(self) -> torch.Tensor:
        """``[V, 3]`` the garment's colours: :data:`CONTACT_RGB` within ``d̂`` of the body, else :data:`GARMENT_RGB`."""
        near = self._near[:, None]
        return torch.where(near, torch.tensor(CONTACT_RGB), torch.tensor(GARMENT_RGB))

    @property
    def mesh_colors(self) -> torch.Tensor:
        """``[V, 3]`` the garment's colours now (:meth:`vertex_colors`)."""
        return self.vertex_colors()

    def time_breakdown(self) -> dict:
        """Seconds per step by phase: ``candidate search`` (the broad phase), ``Newton iterations`` (assembly,
        CCD, line search, friction), ``linear solves``, ``contact view`` (this session's distance queries)."""
        steps = max(self._steps, 1)
        return {
            "steps": self._steps,
            "seconds_per_step": {name: value / steps for name, value in self._phases.items()},
        }

    def summary(self) -> dict:
        """Garment, body and fabric."""
        return {
            "scene": "avatar",
            "garment": self.garment.name,
            "garment_vertices": int(self.garment.vertices.shape[0]),
            "body_vertices": int(self.body_now.shape[0]),
            "capture": self.config.capture,
            "boundary_vertices": int(self.boundary.numel()),
            "motion": self.motion,
            "fabric": {"name": self.fabric_name, **asdict(self.fabric)},
            "newton_iterations_cap": self.newton_iterations,
            "notes": list(self.notes),
        }
