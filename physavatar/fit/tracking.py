"""Mesh tracking with mesh-aligned Gaussians (PhysAvatar §3.1, Eq. 1–4).

Given a multi-view video and the garment mesh at its first frame, recover the garment's vertices in every frame.
One Gaussian rides on each face (:mod:`physavatar.fit.gaussians`); rendering them and comparing with the images moves
the vertices. The body is part of the avatar's mesh as in the paper, but its vertices are known in every frame
(the skinned body, as the paper's SMPL-X fit): its Gaussians occlude the garment and are never moved.

* Frame 1: the vertices are given; optimise the Gaussians' colours, in-plane scales and opacities (garment and
  body) against the images.
* Frames ``1 < t ≤ T``: opacities and scales stay fixed; optimise the garment's vertices and colours against
  ``L_mesh = L_render + λ_i L_iso + λ_n L_normal`` (Eq. 4, ``λ_i = 10``, ``λ_n = 0.1``), starting from the previous
  frame moved on with its velocity.

``L_iso`` (Eq. 2) penalises the change of every 1-ring edge length from the first frame, ``L_normal`` (Eq. 3) the
angle between the normals of faces sharing an edge. The paper writes Eq. 2's summand as a signed difference; a
signed term rewards stretching, so here it is the absolute difference (as in Dynamic 3D Gaussians, which it cites).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from kernels import backend
from physavatar.capture import CameraRig, Capture
from physavatar.fit.gaussians import GaussianAppearance, Subdivision, photometric_loss, render_mesh_gaussians

__all__ = [
    "AvatarGaussians",
    "TrackConfig",
    "TrackResult",
    "fit_first_frame",
    "isometry_loss",
    "mesh_neighbours",
    "normal_loss",
    "track",
]


@dataclass(frozen=True)
class TrackConfig:
    """Settings of :func:`track`.

    Attributes:
        first_iterations: Adam iterations on the first frame (appearance only).
        iterations: Adam iterations on every later frame (vertices and colours).
        lr_vertices: Adam step of the vertices, m.
        lr_colors: Adam step of the colours.
        lr_scales: Adam step of the log-scales.
        lr_opacity: Adam step of the opacity logits.
        lambda_iso: ``λ_i`` of Eq. 4.
        lambda_normal: ``λ_n`` of Eq. 4.
        weight_l1: ``λ`` of Eq. 1.
        normal_scale: thickness of every Gaussian along its face normal, m.
        extrapolate: start each frame from the previous one plus its velocity (else from the previous one).
        iso_tolerance: relative change of each edge's length that Eq. 2 lets pass at no cost (:func:`isometry_loss`);
            0 is the paper's term. Eq. 2 holds every edge at its first-frame length, so the tracked meshes hide the
            fabric's own stretch and the physics estimation (§3.2) reads a stiffer membrane. Measured on the 0.4 m
            sheet of the estimation tests in a stretchy fabric (``κ_s = 0.3``, ``κ_b = 6``: 0.7 % mean strain, 5 % at
            most) swinging for 24 frames, 4 views at 96² px, 100 iterations per frame: with 0 the tracked meshes kept
            0.03 % mean strain and ``κ_s/ρ`` came out 15 % high (``κ_b/ρ`` 4 %); with 0.03 they kept 0.48 % and the
            errors were 8 % and 1 %, with 0.05, 6 % and 1 %. Set it above the fabric's strains and well below the
            distortions that Eq. 2 is there to stop.
        face_subdivisions: levels of 1-to-4 midpoint subdivision of every garment face for the Gaussians: each
            face carries ``4^L`` Gaussians on its sub-triangles, placed and turned by the face's own vertices (which
            stay the only geometric unknowns). 0 is the paper's one Gaussian per face, made for meshes whose faces
            cover a few pixels; on a coarse mesh a face spans many pixels and one elliptical blob cannot cover its
            triangle, so the silhouette and the pattern's edges pull the vertices off the surface.
    """

    first_iterations: int = 200
    iterations: int = 100
    lr_vertices: float = 3e-3
    lr_colors: float = 0.02
    lr_scales: float = 0.01
    lr_opacity: float = 0.05
    lambda_iso: float = 10.0
    lambda_normal: float = 0.1
    weight_l1: float = 0.8
    normal_scale: float = 5e-4
    extrapolate: bool = True
    iso_tolerance: float = 0.0
    face_subdivisions: int = 0

    def __post_init__(self):
        if self.first_iterations < 1 or self.iterations < 1:
            raise ValueError("first_iterations and iterations must be at least 1")
        for name in ("lr_vertices", "lr_colors", "lr_scales", "lr_opacity", "normal_scale"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} ({getattr(self, name)}) must be positive")
        if self.lambda_iso < 0.0 or self.lambda_normal < 0.0 or not 0.0 <= self.weight_l1 <= 1.0:
            raise ValueError("lambda_iso and lambda_normal must be >= 0 and weight_l1 in [0, 1]")
        if not 0.0 <= self.iso_tolerance < 1.0:
            raise ValueError(f"iso_tolerance ({self.iso_tolerance}) is a relative length change in [0, 1)")
        if not 0 <= self.face_subdivisions <= 3:
            raise ValueError(f"face_subdivisions ({self.face_subdivisions}) must be 0 to 3 (64 Gaussians per face)")


@dataclass
class TrackResult:
    """A tracked sequence.

    Attributes:
        vertices: ``[T, V, 3]`` float64 garment vertices per frame, m (frame 0 is the given first mesh).
        colors: ``[T, F, 3]`` each garment face's colour per frame (the mean of its Gaussians'; the input of
            appearance estimation).
        appearance: the garment Gaussians of the first frame (scales, opacities, frame edges), ``F·4^L`` of them
            with :attr:`TrackConfig.face_subdivisions` ``= L``, children of a face next to each other.
        render_loss: ``[T]`` Eq. 1 at the end of each frame's optimisation.
        vertex_error: ``[T]`` mean distance to the true vertices, m, when they were given (else empty).
        frame_time: seconds per frame.
    """

    vertices: torch.Tensor
    colors: torch.Tensor
    appearance: GaussianAppearance
    render_loss: torch.Tensor
    vertex_error: torch.Tensor
    frame_time: list[float] = field(default_factory=list)


def isometry_loss(
    vertices: torch.Tensor,
    rest_lengths: torch.Tensor,
    edges: torch.Tensor,
    degree: torch.Tensor,
    tolerance: float = 0.0,
) -> torch.Tensor:
    """Eq. 2: ``1/|V| Σ_v Σ_{v′ ∈ N(v)} |‖v₁ − v′₁‖ − ‖v_t − v′_t‖| / |N(v)|``, m.

    With a ``tolerance`` ``τ``, each edge's term is ``max(0, |‖v₁ − v′₁‖ − ‖v_t − v′_t‖| − τ ‖v₁ − v′₁‖)``: length
    changes up to ``τ`` of the first frame's length (a fabric's own stretch) cost nothing
    (:attr:`TrackConfig.iso_tolerance`).

    Args:
        vertices: ``[V, 3]`` this frame's vertices.
        rest_lengths: ``[E]`` the first frame's length of each directed 1-ring edge.
        edges: ``[E, 2]`` directed edges ``(v, v′)`` (both directions of every mesh edge).
        degree: ``[V]`` ``|N(v)|``.
        tolerance: ``τ``, a relative length change (0: the paper's term).
    """
    lengths = torch.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], dim=1)
    change = (rest_lengths - lengths).abs()
    if tolerance > 0.0:
        change = (change - tolerance * rest_lengths).clamp_min(0.0)
    per_edge = change / degree[edges[:, 0]]
    return per_edge.sum() / vertices.shape[0]


def normal_loss(vertices: torch.Tensor, faces: torch.Tensor, face_pairs: torch.Tensor) -> torch.Tensor:
    """Eq. 3: ``1/|F| Σ_f Σ_{f′ ∈ N(f)} (1 − n(f)·n(f′))`` over faces sharing an edge (``face_pairs [P, 2]``,
    each unordered pair once, so it is counted twice as in the double sum)."""
    tri = vertices[faces]
    n = torch.nn.functional.normalize(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    return 2.0 * (1.0 - (n[face_pairs[:, 0]] * n[face_pairs[:, 1]]).sum(1)).sum() / faces.shape[0]


def mesh_neighbours(faces: torch.Tensor, vertex_count: int):
    """Directed 1-ring edges ``[E, 2]``, vertex degrees ``[V]`` and edge-adjacent face pairs ``[P, 2]``."""
    f = faces.shape[0]
    half = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = torch.arange(f, device=faces.device).repeat(3)
    key = torch.minimum(half[:, 0], half[:, 1]) * vertex_count + torch.maximum(half[:, 0], half[:, 1])
    order = torch.argsort(key)
    key, owner = key[order], owner[order]
    shared = (key[1:] == key[:-1]).nonzero().squeeze(1)
    face_pairs = torch.stack([owner[shared], owner[shared + 1]], 1)
    unique = torch.unique(key)
    a, b = unique // vertex_count, unique % vertex_count
    edges = torch.cat([torch.stack([a, b], 1), torch.stack([b, a], 1)])
    degree = torch.bincount(edges[:, 0], minlength=vertex_count).clamp_min(1).to(torch.float64)
    return edges, degree, face_pairs


def _concat(
    garment: GaussianAppearance, body: GaussianAppearance, garment_colors: torch.Tensor, body_colors: torch.Tensor
) -> GaussianAppearance:
    """Garment Gaussians followed by the body's, each in the colours given."""
    return GaussianAppearance(
        torch.cat([garment_colors, body_colors]),
        torch.cat([garment.log_scales, body.log_scales]),
        torch.cat([garment.opacity_logits, body.opacity_logits]),
        garment.normal_scale,
        torch.cat([garment.edge, body.edge]),
    )


@dataclass
class AvatarGaussians:
    """The dressed avatar's Gaussians and the cameras they are rendered into: the garment's on the ``4^L``
    sub-triangles of each face, then the body's (one per face), as :func:`fit_first_frame` fits them.

    Attributes:
        garment: ``F·4^L`` garment Gaussians (children of a face next to each other).
        body: ``Fb`` body Gaussians.
        subdivision: the garment's subdivision (:class:`~physavatar.fit.gaussians.Subdivision`).
        faces: ``[F·4^L + Fb, 3]`` the sub-triangles, then the body's triangles offset past the fine vertices.
        world_to_camera: ``[C, 4, 4]`` view matrices; ``intrinsics`` ``[C, 4]`` px; ``width``, ``height`` px.
        background: ``[3]`` colour behind the avatar (the capture's).
    """

    garment: GaussianAppearance
    body: GaussianAppearance
    subdivision: Subdivision
    faces: torch.Tensor
    world_to_camera: torch.Tensor
    intrinsics: torch.Tensor
    width: int
    height: int
    background: torch.Tensor

    @classmethod
    def initial(
        cls,
        rig: CameraRig,
        first_vertices: torch.Tensor,
        faces: torch.Tensor,
        body_vertices: torch.Tensor,
        body_faces: torch.Tensor,
        subdivisions: int,
        normal_scale: float,
        background=(1.0, 1.0, 1.0),
    ) -> AvatarGaussians:
        """Grey Gaussians covering the garment's sub-triangles and the body's faces, on the vertices' device."""
        device = first_vertices.device
        v = first_vertices.shape[0]
        fine = Subdivision.of(faces.long().to(device), v, subdivisions)
        body_faces = body_faces.long().to(device)
        return cls(
            GaussianAppearance.initial(fine(first_vertices), fine.faces, normal_scale=normal_scale),
            GaussianAppearance.initial(body_vertices, body_faces, normal_scale=normal_scale),
            fine,
            torch.cat([fine.faces, body_faces + fine.vertex_count(v)]),
            rig.world_to_camera().to(device),
            rig.intrinsics.to(device),
            rig.width,
            rig.height,
            torch.as_tensor(background, dtype=torch.float32, device=device),
        )

    def render(
        self, garment_vertices: torch.Tensor, body_vertices: torch.Tensor, colors: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``[C, H, W, 3]`` the avatar in every camera, the garment at ``[V, 3]`` ``garment_vertices`` (its
        Gaussians' colours replaced by ``colors`` ``[F·4^L, 3]`` when given); differentiable in both."""
        colors = self.garment.colors if colors is None else colors
        return self._splat(garment_vertices, body_vertices, colors, self.body.colors, self.background)

    def garment_coverage(self, garment_vertices: torch.Tensor, body_vertices: torch.Tensor) -> torch.Tensor:
        """``[C, H, W]`` how much of each pixel the garment covers in front of the body: the avatar rendered with
        the garment white and the body and background black (the rendered counterpart of a garment mask)."""
        white, black = torch.ones_like(self.garment.colors), torch.zeros_like(self.body.colors)
        return self._splat(garment_vertices, body_vertices, white, black, torch.zeros_like(self.background))[..., 0]

    def _splat(self, garment_vertices, body_vertices, garment_colors, body_colors, background) -> torch.Tensor:
        """``[C, H, W, 3]``: the garment's Gaussians on its subdivision, then the body's, in these colours."""
        vertices = torch.cat([self.subdivision(garment_vertices), body_vertices.to(garment_vertices)])
        appearance = _concat(self.garment, self.body, garment_colors, body_colors)
        return render_mesh_gaussians(
            vertices, self.faces, appearance, self.world_to_camera, self.intrinsics, self.width, self.height,
            background,
        )[0]  # fmt: skip

    def detach(self) -> AvatarGaussians:
        """A copy whose appearances are detached from any graph."""
        return dataclasses.replace(self, garment=self.garment.detach(), body=self.body.detach())


def fit_first_frame(
    capture: Capture,
    first_vertices: torch.Tensor,
    faces: torch.Tensor,
    body_vertices: torch.Tensor,
    body_faces: torch.Tensor,
    config: TrackConfig,
) -> tuple[AvatarGaussians, float]:
    """The first frame of :func:`track` (§3.1): the Gaussians' colours, in-plane scales and opacities (garment and
    body) fitted to the capture's first images by ``config.first_iterations`` Adam steps on Eq. 1, the vertices held.

    Args:
        capture: the capture; only its first frame and its cameras are read.
        first_vertices: ``[V, 3]`` garment vertices at the first frame, m, on the device to fit on.
        faces: ``[F, 3]`` garment triangles.
        body_vertices: ``[B, 3]`` body vertices at the first frame, m (``B`` may be 0).
        body_faces: ``[Fb, 3]`` body triangles.
        config: iterations, learning rates, subdivision and normal scale.

    Returns:
        The fitted, detached :class:`AvatarGaussians` and Eq. 1 at the last iteration.
    """
    device = first_vertices.device
    x1 = first_vertices.to(torch.float64)
    gaussians = AvatarGaussians.initial(
        capture.rig, x1, faces, body_vertices.to(device, torch.float64), body_faces, config.face_subdivisions,
        config.normal_scale, capture.background,
    )  # fmt: skip
    garment, body = gaussians.garment, gaussians.body
    for appearance in (garment, body):
        for p in (appearance.colors, appearance.log_scales, appearance.opacity_logits):
            p.requires_grad_(True)
    optimiser = torch.optim.Adam(
        [
            {"params": [garment.colors, body.colors], "lr": config.lr_colors},
            {"params": [garment.log_scales, body.log_scales], "lr": config.lr_scales},
            {"params": [garment.opacity_logits, body.opacity_logits], "lr": config.lr_opacity},
        ]
    )
    target = capture.images[0].to(device, torch.float32)
    body0 = body_vertices.to(device, torch.float64)
    for _ in range(config.first_iterations):
        optimiser.zero_grad(set_to_none=True)
        loss = photometric_loss(gaussians.render(x1, body0), target, config.weight_l1)
        loss.backward()
        optimiser.step()
    return gaussians.detach(), float(loss.detach())


@backend.one_torch_thread_on_cpu()
def track(
    capture: Capture,
    first_vertices: torch.Tensor,
    faces: torch.Tensor,
    body_frames: torch.Tensor | None,
    body_faces: torch.Tensor | None,
    config: TrackConfig | None = None,
    truth: torch.Tensor | None = None,
    progress: bool | Callable[[int, float, float], None] = True,
) -> TrackResult:
    """Track the garment through the capture (§3.1).

    On the CPU, torch runs single-threaded meanwhile (:func:`kernels.backend.one_torch_thread_on_cpu`): each
    iteration is hundreds of small tensor operations around the rasterizer's kernels.

    Args:
        capture: ``T`` frames of ``C`` views with their cameras.
        first_vertices: ``[V, 3]`` garment vertices in the first frame, m (the paper's static reconstruction).
        faces: ``[F, 3]`` garment triangles (fixed topology).
        body_frames: ``[T, B, 3]`` body vertices per frame, m, or ``None`` for a garment alone.
        body_faces: ``[Fb, 3]`` body triangles (``None`` with ``body_frames``).
        config: optimisation settings.
        truth: ``[T, V, 3]`` true garment vertices, only to report the per-frame error.
        progress: ``True`` writes one line per frame to stderr; a callable receives ``(frame, loss, error)``.

    Returns:
        :class:`TrackResult`.

    Raises:
        ValueError: frame counts of the capture, body and truth disagree, or the meshes are malformed.
    """
    config = config or TrackConfig()
    frames = capture.images.shape[0]
    v = first_vertices.shape[0]
    if (body_frames is None) != (body_faces is None):
        raise ValueError("pass body_frames and body_faces together (or neither, for a garment alone)")
    if body_frames is None:
        body_frames = first_vertices.new_zeros(frames, 0, 3)
        body_faces = torch.zeros(0, 3, dtype=torch.int64)
    if body_frames.shape[0] != frames:
        raise ValueError(
            f"the capture has {frames} frames but body_frames has {body_frames.shape[0]}; pass one body pose per frame"
        )
    if truth is not None and tuple(truth.shape) != (frames, v, 3):
        raise ValueError(f"truth must be [{frames}, {v}, 3] (frames, garment vertices), got {tuple(truth.shape)}")
    if first_vertices.dim() != 2 or first_vertices.shape[1] != 3:
        raise ValueError(f"first_vertices must be [V, 3], got {tuple(first_vertices.shape)}")
    if faces.dim() != 2 or faces.shape[1] != 3 or int(faces.max()) >= v or int(faces.min()) < 0:
        raise ValueError(f"faces must be [F, 3] indices into the {v} garment vertices")

    device = backend.torch_device()
    faces = faces.long().to(device)
    edges, degree, face_pairs = mesh_neighbours(faces, v)
    edges, degree, face_pairs = edges.to(device), degree.to(device), face_pairs.to(device)
    x1 = first_vertices.to(device, torch.float64)
    rest_lengths = torch.linalg.norm(x1[edges[:, 0]] - x1[edges[:, 1]], dim=1)
    bodies = body_frames.to(device, torch.float64)

    out_vertices = [x1.clone()]
    out_colors = []
    losses, errors, times = [], [], []

    # Frame 1: appearance only.
    start = time.perf_counter()
    gaussians, first_loss = fit_first_frame(capture, x1, faces, bodies[0], body_faces, config)
    fine = gaussians.subdivision
    colors = gaussians.garment.colors.clone()
    out_colors.append(_per_face(colors, fine))
    losses.append(first_loss)
    errors.append(_error(x1, truth, 0))
    times.append(time.perf_counter() - start)
    _report(progress, 0, frames, losses[-1], errors[-1], times[-1])

    # Later frames: vertices and colours.
    for t in range(1, frames):
        start = time.perf_counter()
        previous = out_vertices[-1]
        guess = previous + (previous - out_vertices[-2]) if config.extrapolate and t > 1 else previous
        x = guess.clone().requires_grad_(True)
        colors = colors.clone().requires_grad_(True)
        optimiser = torch.optim.Adam(
            [{"params": [x], "lr": config.lr_vertices}, {"params": [colors], "lr": config.lr_colors}]
        )
        schedule = torch.optim.lr_scheduler.LambdaLR(
            optimiser,
            lambda i: 0.1 ** (i / config.iterations),  # decays ten-fold over the frame
        )
        target = capture.images[t].to(device, torch.float32)
        for _ in range(config.iterations):
            optimiser.zero_grad(set_to_none=True)
            loss = photometric_loss(gaussians.render(x, bodies[t], colors), target, config.weight_l1)
            total = (
                loss
                + config.lambda_iso * isometry_loss(x, rest_lengths, edges, degree, config.iso_tolerance)
                + config.lambda_normal * normal_loss(x, faces, face_pairs)
            )
            total.backward()
            optimiser.step()
            schedule.step()
        x = x.detach()
        colors = colors.detach()
        out_vertices.append(x)
        out_colors.append(_per_face(colors, fine))
        losses.append(loss.item())
        errors.append(_error(x, truth, t))
        times.append(time.perf_counter() - start)
        _report(progress, t, frames, losses[-1], errors[-1], times[-1])

    return TrackResult(
        torch.stack(out_vertices).cpu(),
        torch.stack(out_colors).cpu(),
        gaussians.garment,
        torch.tensor(losses),
        torch.tensor(errors) if truth is not None else torch.zeros(0),
        times,
    )


def _per_face(colors: torch.Tensor, fine: Subdivision) -> torch.Tensor:
    """Each garment face's colour: the mean of its Gaussians' (``[F·4^L, 3]`` → ``[F, 3]``)."""
    return colors.detach().view(-1, fine.children, 3).mean(1)


def _error(x: torch.Tensor, truth: torch.Tensor | None, t: int) -> float:
    if truth is None:
        return math.nan
    return float(torch.linalg.norm(x.cpu() - truth[t].to(torch.float64), dim=1).mean())


def _report(progress, t: int, frames: int, loss: float, error: float, seconds: float) -> None:
    if callable(progress):
        progress(t, loss, error)
    elif progress:
        err = "" if math.isnan(error) else f", mean vertex error {error * 1e3:.2f} mm"
        print(f"track frame {t + 1}/{frames}: loss {loss:.4f}{err}, {seconds:.1f} s", file=sys.stderr)
