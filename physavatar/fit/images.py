"""The fabric's stiffness from the capture's images, through the physics: §3.1 and §3.2 collapsed into one chain.

The paper estimates the fabric in two steps: it tracks the garment's mesh through the video (§3.1), then fits the
simulator to the tracked meshes (§3.2, Eq. 6). Tracking costs an optimisation per frame, and its regularisers
(Eq. 2's isometry above all) leave their mark on the meshes the physics is fitted to. Here the parameters reach
the pixels directly::

    θ = (log κ_s, log κ_b)  ─►  rollout (Eq. 5, T − 1 implicit steps)  ─►  mesh-aligned Gaussians
        ─►  splatted into the capture's cameras  ─►  Eq. 1 against the images  +  w · (coverage − mask)²

The Gaussians' colours, scales and opacities are those of the tracker's first frame (:func:`fit_first_frame`,
the only appearance optimisation); after it no mesh is tracked. The gradient of the image loss reaches ``θ`` by
two reverse passes chained: torch's through the rasteriser to the ``[T, V, 3]`` frames, then the rollout's adjoint
(:class:`physavatar.cloth.ClothRollout`, ``docs/adjoint.md``) from the frames to the parameters — one backward
solve per step whatever the number of parameters, so the stiffness can vary per garment region as cheaply.
The frames are rendered one at a time and their image gradients summed into one ``[T, V, 3]`` load, so memory
holds one frame's rasterisation, never the whole video's.

The mask term compares the capture's garment masks with the garment's rendered coverage (the avatar rendered with
a white garment in front of a black body; :meth:`AvatarGaussians.garment_coverage`): it pulls on the silhouette,
where the photometric term sees little when garment and background colours are alike.

As in :mod:`physavatar.fit.regions`, ``ρ`` stays at its initial value: gravity and inertia scale together with it,
so only the ratios ``κ/ρ`` are identifiable (:mod:`physavatar.fit.estimation`). L-BFGS with a strong-Wolfe line
search minimises the loss over the parameters' logarithms, each evaluation one rollout forward, ``T − 1`` frames
rendered forward and back, and one adjoint.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from kernels import backend
from physavatar.capture import Capture, Lighting
from physavatar.cloth import STIFFNESS_RANGE, ClothConfig, RolloutScene, rollout
from physavatar.fit.estimation import FabricParameters
from physavatar.fit.gaussians import photometric_loss
from physavatar.fit.regions import check_regions
from physavatar.fit.tracking import AvatarGaussians, TrackConfig, fit_first_frame

__all__ = ["ImageEstimate", "ImageFitConfig", "SunRelighting", "estimate_images", "image_loss"]

F64 = torch.float64
NEWTON_CAP = 400
"""Newton iterations a step of the fit's rollouts may take (at least): the adjoint needs every step converged, and
with the membrane's clamped (modified-Newton) Hessian a soft fabric's step converges linearly: the synthetic
skirt's second step at ``κ_s = 0.8`` needs more than the solver's default 50."""
REJECTED = 10.0
"""The loss, relative to the start's, that a line-search trial gets with a zero gradient when its stiffness leaves
the paper's range (:data:`physavatar.cloth.STIFFNESS_RANGE`) or its rollout does not converge: a step too far (the
strong-Wolfe search extrapolates up to tenfold), from which the search steps back."""


@dataclass(frozen=True)
class ImageFitConfig:
    """Settings of :func:`estimate_images`.

    Attributes:
        iterations: L-BFGS iterations (each one or a few evaluations; at most ``2 × iterations`` evaluations).
        weight_mask: ``w``, the weight of the mean squared difference between the garment's rendered coverage and
            the capture's garment mask, beside Eq. 1 (0 turns the mask term off). Squared, not absolute: the
            coverage of splatted Gaussians is soft where a mask is binary, and the absolute difference's kinks at
            every edge pixel stalled the line search. Off by default: on the pipeline's full-size synthetic capture
            (24 frames, 8 views at 256²) from ``κ_s = 2``, ``κ_b = 0.5``, 10 iterations on an H200 ended at
            +4.8 % / +0.7 % without it and at +63 % / −37 % with ``w = 1``, whose soft-against-binary floor
            (0.03, against Eq. 1's 0.04) steers the search more than the motion does.
        newton_tolerance: the Newton tolerance of the fit's rollouts, m/s (``None``: the fabric's). 1e-3 m/s leaves
            a step 40 µm from its minimiser, but over the workload's 23 steps (skirt, walk) the rollout at the truth
            ends 0.44 mm (mean) from the fabric's own at 1e-4, as far as ``κ_s`` 3 % off moves it (0.45 mm at 0.97,
            0.38 mm at 1.03): the stiff side of the truth barely moves the garment, so that error alone shifts the
            loss's minimum by a per cent or two (see ``garment_pixels``). The fabric's 1e-4 costs about 1.4× the
            rollout. Measured on an H200 with the garment's pixels, on the pipeline's full-size synthetic capture
            (24 frames, 8 views at 256², 15 iterations from ``κ_s = 2``, ``κ_b = 0.5``; truth 1, 1): 1e-3 ended at
            +0.8 % / +0.2 % in 57.2 s, 1e-4 at −0.6 % / −0.1 % in 67.3 s (and −0.9 % / −0.2 % in a first run that
            also compiled the kernels). Both are well within the fit's 3 %; 1e-3 keeps it under a minute.
        garment_pixels: Eq. 1 weighted by the capture's garment masks (:func:`photometric_loss`'s ``weights``), not
            over the whole image. The appearance is the first frame's; in later frames the body's and the splats'
            footprint beyond the garment's silhouette mismatch the images (the loss's floor grows from 0.014 on
            the first frame to 0.078 on the 20th) and, outside the garment, that mismatch favours a softer fabric.
            Measured on the CPU with :func:`image_loss` along each ratio (the ``estimate_images`` workload's
            skirt, 24 frames of the walk, 4 views at 128², the first frame's appearance fit, rollouts at the
            fabric's 1e-4 m/s; truth 1): over the whole image the minimum sits at the edge of a cliff, ``κ_s``
            0.96 (0.95: +13 %, the truth +0.25 %); over the garment's pixels it sits between 1.00 and 1.03 (a
            parabola's vertex at 1.015; 0.94: +24 %, 0.96: +0.11 %, 0.97: +0.05 %, 1.00: +0.002 %, 1.06: +0.10 %),
            and ``κ_b`` at the truth either way (0.9: +39 %, 1.1: +2.1 % over the garment). With rollouts at 1e-3
            the garment's vertex moves to 1.023. Still shallow on the stiff side: within 3 % above the
            truth the garment barely moves, so the fit's precision there stays about a per cent or two. On an H200
            (the full-size capture above, rollouts at 1e-3), the whole image's loss ended at −1.0 %, −3.4 %,
            −1.9 % and −1.7 % in four runs of the same code; the garment's pixels at +0.8 % (and, at 1e-4, −0.9 %
            and −0.6 %).
        appearance: the first frame's appearance fit and the Gaussians' layout (:class:`TrackConfig`: its
            ``first_iterations``, learning rates, ``weight_l1``, ``face_subdivisions`` and ``normal_scale``).
        relight: when the capture's light is known (a synthetic capture's ``lighting``), the garment's colours
            follow its faces' turn toward the sun (:class:`SunRelighting`); else they stay the first frame's. Off
            by default, measured: on the pipeline's full-size synthetic capture (H200, 15 iterations from
            ``κ_s = 2``, ``κ_b = 0.5``) the fit ended at −3.4 % / +0.7 % relit and −1.0 % / +0.2 % without it. The
            image loss is nearly flat on the stiff side of the truth (on the CPU it rises 3 % from 0.94 to 0.97 of
            ``κ_s`` and 0.2 % from 0.97 to 1.03), so which of two close appearance models matches the ray-traced
            images best decides where in that flat stretch the fit stops.
    """

    iterations: int = 15
    weight_mask: float = 0.0
    newton_tolerance: float | None = 1e-3
    garment_pixels: bool = True
    relight: bool = False
    appearance: TrackConfig = TrackConfig()

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations ({self.iterations}) must be at least 1")
        if self.newton_tolerance is not None and not self.newton_tolerance > 0.0:
            raise ValueError(f"newton_tolerance ({self.newton_tolerance}) must be positive, m/s, or None")
        if not (math.isfinite(self.weight_mask) and self.weight_mask >= 0.0):
            raise ValueError(f"weight_mask ({self.weight_mask}) must be a finite number >= 0")


@dataclass(frozen=True)
class ImageEstimate:
    """What :func:`estimate_images` found.

    Attributes:
        density: ``ρ`` held fixed, kg/m³.
        kappa_s, kappa_b: ``[R]`` float64 factors, one per region (``R = 1``: the global fit).
        regions: ``[F]`` int64 region of each face, or ``None`` for the global fit.
        loss: the image loss at the start, at each evaluation (line-search trials included) and at the end (the
            lowest evaluated: where the last line search left the parameters, or the best point before it when a
            search cut short by the evaluation budget ended above it).
        history: the (global) parameters of each entry of ``loss``.
        evaluations: image losses evaluated (all but the first and the last with a backward).
        rejected: line-search trials out of the stiffness range or whose rollout did not converge (given
            :data:`REJECTED`): their ``κ_s`` of each region, then their ``κ_b``.
        appearance_seconds: the first frame's appearance fit, s.
        seconds: the whole estimate, appearance included, s.
    """

    density: float
    kappa_s: torch.Tensor
    kappa_b: torch.Tensor
    regions: torch.Tensor | None
    loss: list[float]
    history: list[FabricParameters]
    evaluations: int
    rejected: list[list[float]]
    appearance_seconds: float
    seconds: float

    @property
    def parameters(self) -> FabricParameters:
        """The global fit as :class:`FabricParameters` (the face-weighted geometric mean of the regions')."""
        return _global(self.density, self.kappa_s, self.kappa_b, self.regions)

    def to_dict(self) -> dict:
        """The estimate as JSON-ready values."""
        out = {
            "density": self.density,
            "kappa_s": self.kappa_s.tolist(),
            "kappa_b": self.kappa_b.tolist(),
            "loss": self.loss,
            "evaluations": self.evaluations,
            "rejected": self.rejected,
            "appearance_seconds": self.appearance_seconds,
            "seconds": self.seconds,
        }
        if self.regions is not None:
            out["faces_per_region"] = torch.bincount(self.regions, minlength=len(self.kappa_s)).tolist()
        return out


def _global(density: float, kappa_s: torch.Tensor, kappa_b: torch.Tensor, regions: torch.Tensor | None):
    """One :class:`FabricParameters` for per-region factors: their face-weighted geometric mean."""
    kappa_s, kappa_b = kappa_s.detach().cpu(), kappa_b.detach().cpu()
    if regions is None:
        return FabricParameters(density, float(kappa_s[0]), float(kappa_b[0]))
    share = torch.bincount(regions.cpu(), minlength=len(kappa_s)).to(F64) / regions.numel()
    return FabricParameters(density, *(float(torch.exp((share * k.log()).sum())) for k in (kappa_s, kappa_b)))


class SunRelighting:
    """The garment's colours as its faces turn toward or away from the capture's sun.

    The first frame's appearance fit gives each garment Gaussian one colour, which holds its albedo times the light it
    received there: ``c = ρ ⊙ (L_a · AO + L_s · max(0, n̂₀ · l̂) · V)`` (:mod:`physavatar.capture.shading`). As the
    garment moves its sub-triangle's normal ``n̂_t`` turns, and so does the sun's share. With the ambient occlusion
    and the sun's visibility taken as they were on the first frame, the colour at frame ``t`` is

        c_t = c ⊙ (L_a + L_s · max(0, n̂_t · l̂)) / (L_a + L_s · max(0, n̂₀ · l̂)),

    differentiable in the vertices through ``n̂_t``. Each normal is turned away from the body (the side a camera
    sees of a garment worn over it), chosen on the first frame and kept. Without it the fixed colours read a fold
    that turns toward the sun as a wrong position, which biases the stiffness the fit finds.

    Args:
        gaussians: the avatar's Gaussians (their garment subdivision).
        first_vertices: ``[V, 3]`` the garment on the first frame, m (the frame the colours were fitted on).
        body_vertices: ``[B, 3]`` the body on the first frame, m (``B = 0``: normals turned away from the garment's
            centroid).
        lighting: the capture's light.
    """

    def __init__(
        self, gaussians: AvatarGaussians, first_vertices: torch.Tensor, body_vertices: torch.Tensor, lighting: Lighting
    ):
        self.subdivision = gaussians.subdivision
        x = first_vertices.detach()
        normals, centres = self._frames(x)
        body = body_vertices.detach().to(x)
        if body.shape[0]:
            nearest = torch.cat([body[torch.cdist(c, body).argmin(1)] for c in centres.split(1 << 14)])
        else:
            nearest = centres.mean(0, keepdim=True).expand_as(centres)
        side = torch.sign((normals * (centres - nearest)).sum(-1))
        self.side = torch.where(side == 0, torch.ones_like(side), side)
        self.ambient, self.sun, self.to_sun = (
            torch.tensor(v, dtype=x.dtype, device=x.device)
            for v in (lighting.ambient, lighting.sun, lighting.sun_direction)
        )
        self.first = self._light(normals)

    def _frames(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unit normals and centres ``[F·4^L, 3]`` of the garment's sub-triangles."""
        fine = self.subdivision(vertices)[self.subdivision.faces]
        normals = torch.linalg.cross(fine[:, 1] - fine[:, 0], fine[:, 2] - fine[:, 0])
        return normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-30), fine.mean(1)

    def _light(self, normals: torch.Tensor) -> torch.Tensor:
        facing = (self.side * (normals @ self.to_sun)).clamp_min(0.0)
        return self.ambient + self.sun * facing[:, None]

    def colors(self, colors: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """``[F·4^L, 3]`` the Gaussians' ``colors`` relit for the garment at ``[V, 3]`` ``vertices``."""
        light = self._light(self._frames(vertices)[0])
        return colors * (light / self.first).to(colors.dtype)


def image_loss(
    gaussians: AvatarGaussians,
    frames: torch.Tensor,
    body_frames: torch.Tensor,
    images: torch.Tensor,
    masks: torch.Tensor,
    weight_l1: float,
    weight_mask: float,
    backward: bool = False,
    relighting: SunRelighting | None = None,
    garment_pixels: bool = False,
) -> tuple[float, torch.Tensor | None]:
    """The image loss of a garment sequence, and its gradient in the garment's vertices.

    ``L = 1/(T − 1) Σ_{t ≥ 1} [Eq. 1(render_t, image_t) + w · mean (coverage_t − mask_t)²]``; frame 0 is the start
    the appearance was fitted on. With ``garment_pixels`` Eq. 1 is weighted by ``mask_t`` (the garment's pixels of
    the capture; :attr:`ImageFitConfig.garment_pixels`). Frames are rendered one at a time; with ``backward``
    each one's gradient is accumulated before the next is rendered.

    Args:
        gaussians: the avatar's Gaussians and cameras (:func:`fit_first_frame`).
        frames: ``[T, V, 3]`` garment vertices per frame, m (read only: the gradient is returned, not propagated).
        body_frames: ``[T, B, 3]`` body vertices per frame, m.
        images: ``[T, C, H, W, 3]`` the capture's images in [0, 1], on the Gaussians' device.
        masks: ``[T, C, H, W]`` float garment masks in {0, 1}, same device.
        weight_l1: ``λ`` of Eq. 1.
        weight_mask: ``w``.
        backward: also return ``∂L/∂frames`` ``[T, V, 3]`` (zero at frame 0).
        relighting: the garment's colours follow its faces' turn toward the sun (:class:`SunRelighting`); ``None``:
            fixed colours.
        garment_pixels: Eq. 1 over the capture's garment pixels only.

    Returns:
        ``(L, ∂L/∂frames or None)``.
    """
    count = frames.shape[0]
    leaf = frames.detach().requires_grad_(backward)
    total = 0.0
    for t in range(1, count):
        with torch.set_grad_enabled(backward):
            colors = None if relighting is None else relighting.colors(gaussians.garment.colors, leaf[t])
            render = gaussians.render(leaf[t], body_frames[t], colors)
            loss = photometric_loss(render, images[t], weight_l1, masks[t] if garment_pixels else None)
            if weight_mask > 0.0:
                coverage = gaussians.garment_coverage(leaf[t], body_frames[t])
                loss = loss + weight_mask * (coverage - masks[t]).square().mean()
            loss = loss / (count - 1)
        if backward:
            loss.backward()
        total += float(loss.detach())
    if not backward:
        return total, None
    return total, leaf.grad if leaf.grad is not None else torch.zeros_like(leaf)


def estimate_images(
    capture: Capture,
    first_vertices: torch.Tensor,
    faces: torch.Tensor,
    body_frames: torch.Tensor,
    body_faces: torch.Tensor,
    boundary_index: torch.Tensor,
    boundary_targets: torch.Tensor,
    fabric: ClothConfig,
    initial: FabricParameters,
    config: ImageFitConfig | None = None,
    regions: torch.Tensor | None = None,
    gaussians: AvatarGaussians | None = None,
    device: str | None = None,
    progress: Callable[[int, float, list[float], list[float]], None] | None = None,
) -> ImageEstimate:
    """Fit ``κ_s`` and ``κ_b`` (globally, or per region) to the capture's images through the garment's rollout.

    Args:
        capture: ``T`` frames of ``C`` views, their garment masks and cameras; one step of ``1 / fps`` per frame.
        first_vertices: ``[V, 3]`` the garment at the first frame, m: the rollout's start (at rest, zero velocity)
            and its rest shape.
        faces: ``[F, 3]`` garment triangles.
        body_frames: ``[T, B, 3]`` body vertices per frame, m; ``body_faces`` ``[Fb, 3]`` its triangles.
        boundary_index: ``[D]`` Dirichlet garment vertices; ``boundary_targets`` ``[T, D, 3]`` their positions, m.
        fabric: the simulator's settings (its density, stiffness factors are replaced).
        initial: ``ρ`` (held) and the starting ``κ_s``, ``κ_b`` (of every region).
        config: iterations, mask weight and the appearance fit.
        regions: ``[F]`` int64 region of each face, ``0..R−1`` (:func:`physavatar.fit.garment_regions`); ``None``
            fits one global pair.
        gaussians: the avatar's Gaussians when they are known (e.g. the tracker's); ``None`` fits them to the first
            frame (:func:`fit_first_frame` with ``config.appearance``). Their cameras are used, not the capture's.
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the backend's device or picks the default.
        progress: called after each evaluation with ``(evaluation, loss, κ_s per region, κ_b per region)``.

    Returns:
        :class:`ImageEstimate`.

    Raises:
        ValueError: frame counts of the capture, body and targets that differ; ``regions`` not one integer per face
            or with an empty region; a rollout step that does not converge.
    """
    config = config or ImageFitConfig()
    frames = capture.images.shape[0]
    for name, sequence in (("body_frames", body_frames), ("boundary_targets", boundary_targets)):
        if sequence.shape[0] != frames:
            raise ValueError(
                f"the capture has {frames} frames but {name} has {sequence.shape[0]}; the capture and the body "
                "motion must come from one recording"
            )
    if frames < 2:
        raise ValueError(f"the capture must hold at least 2 frames (a start and one step), got {frames}")
    faces = torch.as_tensor(faces).long()
    count = 1
    if regions is not None:
        regions = check_regions(regions, faces.shape[0])
        count = int(regions.max()) + 1
    backend.init(device)
    dev = backend.torch_device()
    start = time.perf_counter()
    x0 = torch.as_tensor(first_vertices).to(dev, F64)
    body = torch.as_tensor(body_frames).to(dev, F64)
    body_faces = torch.as_tensor(body_faces).long().to(dev)
    targets = torch.as_tensor(boundary_targets).to(dev, F64)
    if gaussians is None:
        with backend.one_torch_thread_on_cpu():
            gaussians, _ = fit_first_frame(capture, x0, faces.to(dev), body[0], body_faces, config.appearance)
    appearance_seconds = time.perf_counter() - start
    images = capture.images.to(dev, torch.float32)
    masks = capture.masks.to(dev, torch.float32)
    relighting = None
    if config.relight and capture.lighting is not None:
        relighting = SunRelighting(gaussians, x0, body[0], capture.lighting)
    fabric = dataclasses.replace(
        fabric,
        max_newton_iterations=max(fabric.max_newton_iterations, NEWTON_CAP),
        newton_tolerance=config.newton_tolerance or fabric.newton_tolerance,
    )
    scene = RolloutScene(
        x0, faces.to(dev), body_faces, torch.as_tensor(boundary_index).long().to(dev), 1.0 / capture.fps, fabric
    )
    index = None if regions is None else regions.to(dev)
    log_s = torch.full((count,), math.log(initial.kappa_s), dtype=F64, device=dev, requires_grad=True)
    log_b = torch.full((count,), math.log(initial.kappa_b), dtype=F64, device=dev, requires_grad=True)

    def simulate() -> torch.Tensor:
        if index is None:
            return rollout(scene, initial.density, log_s.exp()[0], log_b.exp()[0], x0, body, targets)
        fields = {"kappa_s_field": log_s.exp()[index], "kappa_b_field": log_b.exp()[index]}
        return rollout(scene, initial.density, 1.0, 1.0, x0, body, targets, **fields)

    def evaluate(backward: bool) -> float:
        with torch.set_grad_enabled(backward):
            sequence = simulate()
        with backend.one_torch_thread_on_cpu():
            loss, grad = image_loss(
                gaussians, sequence, body, images, masks, config.appearance.weight_l1, config.weight_mask, backward,
                relighting, config.garment_pixels,
            )  # fmt: skip
        if backward:
            sequence.backward(grad * scale)
        return loss

    scale = 1.0
    with torch.no_grad():
        first = evaluate(False)
    scale = 1.0 / max(first, 1e-300)  # L-BFGS's tolerances are absolute: fit the loss relative to where it starts
    history = [first]

    def now() -> FabricParameters:
        return _global(float(initial.density), log_s.exp(), log_b.exp(), regions)

    parameters, rejected = [now()], []
    optimiser = torch.optim.LBFGS(
        [log_s, log_b], lr=1.0, max_iter=config.iterations, max_eval=2 * config.iterations, tolerance_grad=1e-9,
        tolerance_change=1e-12, history_size=10, line_search_fn="strong_wolfe",
    )  # fmt: skip

    def closure() -> torch.Tensor:
        optimiser.zero_grad()
        values = torch.cat([log_s, log_b]).detach().exp()
        if bool(((values < STIFFNESS_RANGE[0]) | (values > STIFFNESS_RANGE[1])).any()):
            rejected.append(values.tolist())  # a line-search trial outside the paper's range: the simulator refuses it
            return torch.tensor(REJECTED, dtype=F64)
        try:
            loss = evaluate(True)
        except ValueError as error:  # a line-search trial too far out for the steps to converge: reject it
            if "did not converge" not in str(error):
                raise
            rejected.append(values.tolist())
            return torch.tensor(REJECTED, dtype=F64)
        history.append(loss)
        parameters.append(now())
        if loss < best[0]:
            best[:] = [loss, log_s.detach().clone(), log_b.detach().clone()]
        if progress is not None:
            progress(len(history) - 1, loss, log_s.detach().exp().tolist(), log_b.detach().exp().tolist())
        return torch.tensor(loss * scale, dtype=F64)

    best = [first, log_s.detach().clone(), log_b.detach().clone()]
    optimiser.step(closure)
    with torch.no_grad():
        history.append(evaluate(False))  # where the last line search left the parameters
        if history[-1] > best[0]:  # a search cut short by the evaluation budget can end above its best point
            log_s.copy_(best[1])
            log_b.copy_(best[2])
            history[-1] = best[0]
    parameters.append(now())
    return ImageEstimate(
        float(initial.density),
        log_s.detach().exp().cpu(),
        log_b.detach().exp().cpu(),
        None if regions is None else regions.cpu(),
        history,
        parameters,
        len(history),
        rejected,
        appearance_seconds,
        time.perf_counter() - start,
    )
