"""What drives a garment frame by frame: the body collider and the boundary vertices (PhysAvatar §3.2, Eq. 5).

A step from frame ``t`` to ``t + 1`` moves the body collider from its frame-``t`` to its frame-``t+1`` vertices and
puts the boundary vertices ``V^b_{t+1}`` on their skinned targets (Appendix A.3.2). :class:`BodyDriver` holds both
sequences, made once from a motion (:meth:`BodyDriver.from_motion`) or given (a capture's body fit), and hands out
the :class:`~physavatar.cloth.ClothControl` of each step. :func:`drive_captured_garment` makes a captured garment
simulable over its capture's body sequence: the preparation stage writes what it returns, the interactive session
plays it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from physavatar.body import Body, Motion, attach_to_surface
from physavatar.cloth import ClothControl
from physavatar.garment import Garment, boundary_targets, select_boundary
from physavatar.intersections import IntersectionReport, resolve_intersections

__all__ = ["GAP_OVER_CONTACT_DISTANCE", "BodyDriver", "CapturedGarment", "drive_captured_garment"]

GAP_OVER_CONTACT_DISTANCE = 2.0
"""Clearance a captured garment is given from the frame-0 body, in barrier activation distances ``d̂``
(:func:`drive_captured_garment`): a vertex closer than ``d̂`` would start inside the barrier's support, one at 0
would make it infinite."""


@dataclass(frozen=True, eq=False)
class BodyDriver:
    """The body and the garment's boundary vertices over ``T`` frames, one implicit step of ``dt`` between frames.

    Attributes:
        body_frames: ``[T, B, 3]`` body collider vertices per frame, m.
        boundary_index: ``[D]`` int64 Dirichlet garment vertices.
        boundary_targets: ``[T, D, 3]`` their positions per frame, m.
        fps: frames per second; ``dt = 1 / fps`` s.
    """

    body_frames: torch.Tensor
    boundary_index: torch.Tensor
    boundary_targets: torch.Tensor
    fps: float

    def __post_init__(self):
        frames, index, targets = self.body_frames, self.boundary_index, self.boundary_targets
        if frames.dim() != 3 or frames.shape[2] != 3 or targets.dim() != 3 or targets.shape[2] != 3:
            raise ValueError(
                f"body_frames must be [T, B, 3] and boundary_targets [T, D, 3], got {list(frames.shape)} and "
                f"{list(targets.shape)}"
            )
        if index.dim() != 1 or targets.shape[:2] != (frames.shape[0], index.numel()):
            raise ValueError(
                f"boundary_targets {list(targets.shape)} must hold one [D, 3] row per body frame ({frames.shape[0]}) "
                f"for the {index.numel()} boundary vertices"
            )
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")

    @staticmethod
    def check_steps(motion: Motion, steps: int) -> None:
        """Raise ``ValueError``, naming the fix, unless ``motion`` holds the ``steps + 1`` poses of ``steps`` steps."""
        if steps < 1 or steps + 1 > motion.num_frames:
            raise ValueError(
                f"frames ({steps}) must lie in 1..{motion.num_frames - 1}: the motion holds {motion.num_frames} poses "
                "and each step needs the next one; make the motion longer or ask for fewer frames"
            )

    @staticmethod
    def from_motion(
        body: Body, motion: Motion, garment_vertices: torch.Tensor, boundary_index: torch.Tensor, steps: int
    ) -> BodyDriver:
        """The body skinned through the first ``steps + 1`` poses of ``motion`` and the boundary vertices following
        the skinning of their nearest body points (:func:`physavatar.garment.boundary_targets`).

        Args:
            body: the skinned body.
            motion: poses; frame 0 is the pose the garment was placed on.
            garment_vertices: ``[V, 3]`` the garment as placed on the body in frame 0, m.
            boundary_index: ``[D]`` its Dirichlet vertices.
            steps: steps to drive.

        Raises:
            ValueError: a motion too short for ``steps`` (each step needs the next pose).
        """
        BodyDriver.check_steps(motion, steps)
        index = boundary_index.long().cpu()
        rotations = motion.rotations[: steps + 1]
        translation = motion.root_translation[: steps + 1]
        return BodyDriver(
            body.skin(rotations, translation),
            index,
            boundary_targets(body, garment_vertices[index], rotations, translation),
            float(motion.fps),
        )

    @staticmethod
    def from_body_frames(
        body_frames: torch.Tensor,
        body_faces: torch.Tensor,
        garment_vertices: torch.Tensor,
        boundary_index: torch.Tensor,
        fps: float,
    ) -> BodyDriver:
        """A captured body (one mesh per frame, no skeleton) and the boundary vertices carried by their nearest body
        triangles (:func:`physavatar.body.attach_to_surface`).

        Args:
            body_frames: ``[T, B, 3]`` body vertices per frame, m.
            body_faces: ``[G, 3]`` the body's triangles.
            garment_vertices: ``[V, 3]`` the garment at frame 0, m.
            boundary_index: ``[D]`` its Dirichlet vertices.
            fps: frames per second of the sequence.
        """
        index = boundary_index.long().cpu()
        frames = body_frames.detach().cpu().to(torch.float64)
        attachment = attach_to_surface(garment_vertices.detach().cpu()[index], frames[0], body_faces)
        return BodyDriver(frames, index, attachment.positions(frames, body_faces.cpu()), float(fps))

    @property
    def frames(self) -> int:
        """``T``, the number of frames (``T − 1`` steps)."""
        return self.body_frames.shape[0]

    @property
    def dt(self) -> float:
        """Step size ``1 / fps``, s."""
        return 1.0 / self.fps

    def to(self, device: torch.device | str) -> BodyDriver:
        """The same driver with its tensors on ``device``, so that :meth:`control` hands out views, no copies."""
        return BodyDriver(
            self.body_frames.to(device), self.boundary_index.to(device), self.boundary_targets.to(device), self.fps
        )

    def control(self, t: int) -> ClothControl:
        """What moves the garment in the step from frame ``t`` to ``t + 1`` (Eq. 5), ``0 <= t < T − 1``."""
        if not 0 <= t < self.frames - 1:
            raise IndexError(f"step {t} is outside 0..{self.frames - 2}: the driver holds {self.frames} frames")
        return ClothControl(
            self.body_frames[t], self.body_frames[t + 1], self.boundary_index, self.boundary_targets[t + 1]
        )


@dataclass(frozen=True, eq=False)
class CapturedGarment:
    """A captured garment made simulable over its capture's body sequence (:func:`drive_captured_garment`).

    Attributes:
        garment: the garment at frame 0, its intersections with the frame-0 body and with itself resolved, m.
        boundary_chosen: ``"given"`` (the capture's boundary file) or ``"automatic"``.
        intersections: what the resolution moved and what is left.
        driver: the body sequence and the boundary vertices carried by their nearest body triangles.
    """

    garment: Garment
    boundary_chosen: str
    intersections: IntersectionReport
    driver: BodyDriver


def drive_captured_garment(
    body_frames: torch.Tensor,
    body_faces: torch.Tensor,
    garment_vertices: torch.Tensor,
    garment_faces: torch.Tensor,
    boundary: torch.Tensor | None,
    fps: float,
    clearance: float,
    name: str = "garment",
) -> CapturedGarment:
    """Resolve a captured garment's intersections with the frame-0 body and with itself to ``clearance``
    (:func:`physavatar.intersections.resolve_intersections`), take ``boundary`` or choose the boundary vertices
    (:func:`physavatar.garment.select_boundary`), and carry them through the body sequence
    (:meth:`BodyDriver.from_body_frames`).

    Args:
        body_frames: ``[T, B, 3]`` body vertices per frame, m (a capture's :attr:`~physavatar.capture.
            CaptureFolder.body_frames`).
        body_faces: ``[G, 3]`` the body's triangles.
        garment_vertices: ``[V, 3]`` the garment at frame 0, m.
        garment_faces: ``[F, 3]`` its triangles.
        boundary: ``[D]`` the capture's boundary vertices, or ``None`` to choose them.
        fps: frames per second of the sequence.
        clearance: the gap left between the garment and the frame-0 body, m (above the barrier's ``d̂``).
        name: the garment's name.
    """
    body0 = body_frames[0]
    resolved, report = resolve_intersections(garment_vertices, garment_faces, body0, body_faces, clearance)
    garment = Garment(resolved, garment_faces, name)
    if boundary is not None:
        chosen = "given"
    else:
        boundary, chosen = select_boundary(garment, (body0, body_faces), mode="auto"), "automatic"
    driver = BodyDriver.from_body_frames(body_frames, body_faces, resolved, boundary, fps)
    return CapturedGarment(garment, chosen, report, driver)
