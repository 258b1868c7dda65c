"""What drives a garment frame by frame: the body collider and the boundary vertices (PhysAvatar §3.2, Eq. 5).

A step from frame ``t`` to ``t + 1`` moves the body collider from its frame-``t`` to its frame-``t+1`` vertices and
puts the boundary vertices ``V^b_{t+1}`` on their skinned targets (Appendix A.3.2). :class:`BodyDriver` holds both
sequences, made once from a motion (:meth:`BodyDriver.from_motion`) or given (a capture's body fit), and hands out
the :class:`~physavatar.cloth.ClothControl` of each step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from physavatar.body import Body, Motion, attach_to_surface
from physavatar.cloth import ClothControl
from physavatar.garment import boundary_targets

__all__ = ["BodyDriver"]


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
