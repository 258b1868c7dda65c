"""Spatially varying stiffness: ``κ_s`` and ``κ_b`` per garment region, fitted through the adjoint of the rollout.

A garment is rarely one fabric: a skirt's waistband, a lined front, a stitched hem. With ``R`` regions the
parameters are ``2R`` stiffness factors, where forward sensitivities
(:meth:`~physavatar.cloth.SolverCloth.sensitivity_step`) would cost ``2R`` extra solves per step; the adjoint
(:class:`physavatar.cloth.ClothRollout`, ``docs/adjoint.md``) costs one backward solve per step whatever ``R``.
:func:`estimate_regions` minimises Eq. 6 (:func:`physavatar.fit.estimation.sim_loss`) over the regions' ``log κ_s``
and ``log κ_b`` by L-BFGS with a strong-Wolfe line search, each evaluation one rollout forward and one backward;
``ρ`` stays at its initial value (only the ratios ``κ/ρ`` are identifiable, :mod:`physavatar.fit.estimation`).
:func:`garment_regions` splits a garment into angular sectors about the vertical axis, the left and right halves
for two.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from kernels import backend
from physavatar.cloth import RolloutScene, rollout
from physavatar.fit.estimation import EstimationProblem, FabricParameters

__all__ = ["RegionEstimate", "check_regions", "estimate_regions", "garment_regions"]


def garment_regions(vertices: torch.Tensor, faces: torch.Tensor, count: int) -> torch.Tensor:
    """``[F]`` int64 region of each face: ``count`` equal angular sectors about the vertical (y) axis through the
    garment's mean vertex, by the azimuth ``atan2(x, z)`` of the face's centroid; for two, ``x < 0`` and ``x ≥ 0``
    (the body's right and left halves, :mod:`physavatar.body`).

    Raises:
        ValueError: ``count`` below 1.
    """
    if int(count) < 1:
        raise ValueError(f"count must be at least 1 region, got {count}")
    x = vertices.detach().cpu().to(torch.float64)
    centroid = x[faces.cpu().long()].mean(1) - x.mean(0)
    azimuth = torch.atan2(centroid[:, 0], centroid[:, 2])  # [-π, π]
    sector = torch.floor((azimuth + math.pi) / (2.0 * math.pi) * int(count)).long()
    return sector.clamp(0, int(count) - 1)


def check_regions(regions: torch.Tensor, face_count: int) -> torch.Tensor:
    """``regions`` as ``[F]`` int64 after checking it numbers the garment's faces ``0..R−1``, each region non-empty.

    Raises:
        ValueError: not one non-negative integer per face, or a region without a face.
    """
    regions = torch.as_tensor(regions).reshape(-1)
    if regions.numel() != face_count or regions.dtype.is_floating_point or int(regions.min()) < 0:
        raise ValueError(f"regions must hold one non-negative integer per garment face ({face_count})")
    regions = regions.long()
    count = int(regions.max()) + 1
    if bool((torch.bincount(regions, minlength=count) == 0).any()):
        raise ValueError(
            f"regions must number 0..R-1 with every region holding a face; got regions {regions.unique().tolist()}"
        )
    return regions


@dataclass(frozen=True)
class RegionEstimate:
    """What :func:`estimate_regions` found.

    Attributes:
        regions: ``[F]`` int64 region of each face.
        density: ``ρ`` held fixed, kg/m³.
        kappa_s, kappa_b: ``[R]`` float64 factors of each region.
        loss: Eq. 6 at the start, at each evaluation of the fit (line-search trials included) and at the end, m².
        evaluations: rollouts run (all but the first and the last with a backward).
        seconds: wall-clock time of the fit.
    """

    regions: torch.Tensor
    density: float
    kappa_s: torch.Tensor
    kappa_b: torch.Tensor
    loss: list[float]
    evaluations: int
    seconds: float

    def to_dict(self) -> dict:
        """The estimate as JSON-ready values (per region, and the faces in each)."""
        counts = torch.bincount(self.regions, minlength=len(self.kappa_s)).tolist()
        return {
            "density": self.density,
            "kappa_s": self.kappa_s.tolist(),
            "kappa_b": self.kappa_b.tolist(),
            "faces_per_region": counts,
            "loss": self.loss,
            "evaluations": self.evaluations,
            "seconds": self.seconds,
        }


def estimate_regions(
    problem: EstimationProblem,
    regions: torch.Tensor,
    initial: FabricParameters,
    iterations: int = 25,
    device: str | None = None,
    progress: Callable[[int, float, list[float], list[float]], None] | None = None,
) -> RegionEstimate:
    """Fit ``κ_s`` and ``κ_b`` per region to the problem's reference frames (Eq. 6), gradients by the adjoint.

    Args:
        problem: reference frames, body, boundary and settings (its ``reference[0]`` is the start, at rest).
        regions: ``[F]`` int64 region of each garment face, ``0..R−1`` (:func:`garment_regions`).
        initial: ``ρ`` (held) and the starting ``κ_s``, ``κ_b`` of every region.
        iterations: L-BFGS iterations (each one or a few rollouts; at most 4 × iterations rollouts in all).
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the backend's device or picks the default.
        progress: called after each rollout with ``(evaluation, loss, κ_s per region, κ_b per region)``.

    Raises:
        ValueError: ``regions`` not one integer per face, or an empty region; a rollout step that does not converge.
    """
    faces = problem.faces.long()
    regions = check_regions(regions, faces.shape[0])
    count = int(regions.max()) + 1
    backend.init(device)
    dev = backend.torch_device()
    scene = RolloutScene(
        problem.rest_vertices.to(dev, torch.float64),
        faces.to(dev),
        problem.body_faces.long().to(dev),
        problem.boundary_index.long().to(dev),
        problem.dt,
        problem.config,
    )
    reference = problem.reference.to(dev, torch.float64)
    body, targets = problem.body_frames.to(dev, torch.float64), problem.boundary_targets.to(dev, torch.float64)
    index = regions.to(dev)
    start = time.perf_counter()
    log_s = torch.full((count,), math.log(initial.kappa_s), dtype=torch.float64, device=dev, requires_grad=True)
    log_b = torch.full((count,), math.log(initial.kappa_b), dtype=torch.float64, device=dev, requires_grad=True)

    def loss_at() -> torch.Tensor:
        frames = rollout(
            scene, initial.density, 1.0, 1.0, reference[0], body, targets,
            kappa_s_field=log_s.exp()[index], kappa_b_field=log_b.exp()[index],
        )  # fmt: skip
        return ((frames[1:] - reference[1:]) ** 2).sum()

    with torch.no_grad():
        first = float(loss_at())
    scale = 1.0 / max(first, 1e-300)  # L-BFGS's tolerances are absolute: fit the loss relative to where it starts
    optimiser = torch.optim.LBFGS(
        [log_s, log_b], lr=1.0, max_iter=iterations, max_eval=4 * iterations, tolerance_grad=1e-12,
        tolerance_change=1e-15, history_size=10, line_search_fn="strong_wolfe",
    )  # fmt: skip
    history = [first]

    def closure() -> torch.Tensor:
        optimiser.zero_grad()
        loss = loss_at() * scale
        loss.backward()
        history.append(float(loss.detach()) / scale)
        if progress is not None:
            progress(len(history) - 1, history[-1], log_s.detach().exp().tolist(), log_b.detach().exp().tolist())
        return loss

    optimiser.step(closure)
    with torch.no_grad():
        history.append(float(loss_at()))  # where the last line search left the parameters
    return RegionEstimate(
        regions.cpu(),
        float(initial.density),
        log_s.detach().exp().cpu(),
        log_b.detach().exp().cpu(),
        history,
        len(history),
        time.perf_counter() - start,
    )
