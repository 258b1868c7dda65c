"""Mesh-aligned 3D Gaussians (PhysAvatar §3.1): one Gaussian per face, bound to the mesh, rendered by splatting.

Each face ``f = (v0, v1, v2)`` carries one Gaussian at its barycentre. Its rotation is the face's local frame: the
x-axis along the face's longest edge *at the first frame* (the same edge in every later frame, so the frame turns
with the cloth), the z-axis along the face normal, ``y = z × x``. Its scales are ``(s_x, s_y, s_n)``: two in-plane
scales learnt on the first frame and a small constant normal scale ``s_n`` that keeps the Gaussian on the surface.
Position and rotation therefore follow the vertices, which is how optimising the images moves the mesh.
For a mesh whose faces span many pixels, :class:`Subdivision` puts ``4^L`` Gaussians on each face: one per
triangle of the face's midpoint subdivision, whose vertices are fixed combinations of the face's own.

Rendering is the 3D Gaussian Splatting pipeline (Kerbl et al. 2023): the covariance ``Σ = R S² Rᵀ`` is projected
to the image with the Jacobian of the pinhole projection at the mean (EWA splatting, Zwicker et al. 2002),
``Σ' = J W Σ Wᵀ Jᵀ + 0.3 I`` px² (the 0.3 px² low-pass keeps sub-pixel Gaussians visible), and
:func:`kernels.gaussian_splat.rasterize_gaussians` composites the sorted 2D Gaussians front to back. Everything
here is torch and differentiable in the vertices, colours, scales and opacities.

Cameras follow :class:`physavatar.capture.CameraRig`: NeRF/OpenGL camera-to-world matrices (x right, y up, looking
along −z) and pinhole intrinsics ``(fx, fy, cx, cy)``, shared by every camera or one row per camera
(:attr:`physavatar.capture.CameraRig.intrinsics`), with the image's y axis pointing down.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from kernels.gaussian_splat import rasterize_gaussians
from kernels.image_metrics import ssim, ssim_map

__all__ = [
    "GaussianAppearance",
    "Subdivision",
    "face_frames",
    "longest_edges",
    "photometric_loss",
    "project_gaussians",
    "render_mesh_gaussians",
]

_LOW_PASS = 0.3  # px², 3DGS's screen-space dilation
_NEAR = 0.01  # m


@dataclass
class GaussianAppearance:
    """What the Gaussians of one mesh carry besides their geometry (all per face).

    Attributes:
        colors: ``[F, 3]`` colours, linear values in [0, 1] (clamped when rendered).
        log_scales: ``[F, 2]`` natural logs of the in-plane scales ``(s_x, s_y)``, m.
        opacity_logits: ``[F]`` logits of the opacities.
        normal_scale: ``s_n``, m: the constant thickness along the face normal.
        edge: ``[F]`` int64 index ``k`` of each face's longest edge at the first frame, from vertex ``k`` to
            vertex ``k + 1 (mod 3)``.
    """

    colors: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    normal_scale: float
    edge: torch.Tensor

    @classmethod
    def initial(
        cls,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        color: float = 0.5,
        opacity: float = 0.95,
        normal_scale: float = 5e-4,
    ) -> GaussianAppearance:
        """Grey, nearly opaque Gaussians whose in-plane scales cover their face.

        Args:
            vertices: ``[V, 3]`` the first frame's vertices, m.
            faces: ``[F, 3]`` triangles.
            color: initial grey level.
            opacity: initial opacity in (0, 1).
            normal_scale: ``s_n``, m.
        """
        tri = vertices[faces.long()]
        edge = longest_edges(tri)
        area = 0.5 * torch.linalg.norm(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
        length = torch.linalg.norm(
            tri.gather(1, ((edge + 1) % 3)[:, None, None].expand(-1, 1, 3))[:, 0]
            - tri.gather(1, edge[:, None, None].expand(-1, 1, 3))[:, 0],
            dim=1,
        )
        height = 2.0 * area / length.clamp_min(1e-12)
        # σ ≈ a quarter of the face's extent along and across its longest edge: 2πσ_xσ_y is about its area.
        scales = torch.stack([length / 4.0, height / 3.5], 1).clamp_min(1e-5)
        f = faces.shape[0]
        dtype, device = torch.float32, vertices.device
        return cls(
            colors=torch.full((f, 3), color, dtype=dtype, device=device),
            log_scales=torch.log(scales).to(dtype),
            opacity_logits=torch.full((f,), float(torch.logit(torch.tensor(opacity))), dtype=dtype, device=device),
            normal_scale=normal_scale,
            edge=edge,
        )

    def detach(self) -> GaussianAppearance:
        """A copy whose tensors are detached from any graph."""
        return GaussianAppearance(
            self.colors.detach().clone(),
            self.log_scales.detach().clone(),
            self.opacity_logits.detach().clone(),
            self.normal_scale,
            self.edge.clone(),
        )


@dataclass(frozen=True)
class Subdivision:
    """``L`` levels of 1-to-4 midpoint subdivision of a triangle mesh, as a linear map of its vertices.

    Every level adds one vertex at the midpoint of each edge and splits each triangle ``(a, b, c)`` into
    ``(a, m_ab, m_ca)``, ``(m_ab, b, m_bc)``, ``(m_ca, m_bc, c)`` and ``(m_ab, m_bc, m_ca)`` (orientation kept). The
    ``4^L`` children of face ``f`` are faces ``f·4^L … (f + 1)·4^L − 1`` of :attr:`faces`, so per-child values fold
    back to their parent with ``.view(F, 4^L, ...)``. Calling it maps ``[V, 3]`` vertices, differentiably, to the
    ``[V′, 3]`` vertices of the fine mesh (the first ``V`` are the coarse ones).

    Attributes:
        faces: ``[F·4^L, 3]`` int64 triangles of the fine mesh.
        midpoints: per level, ``[E_l, 2]`` the vertex pairs whose midpoints that level appends.
    """

    faces: torch.Tensor
    midpoints: tuple[torch.Tensor, ...]

    @classmethod
    def of(cls, faces: torch.Tensor, vertex_count: int, levels: int) -> Subdivision:
        """Subdivide ``faces [F, 3]`` (indices into ``vertex_count`` vertices) ``levels`` times (0: unchanged)."""
        faces = faces.long()
        midpoints = []
        count = vertex_count
        for _ in range(levels):
            f = faces.shape[0]
            half = torch.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 1)  # [F, 3, 2]
            edges, slot = torch.unique(half.sort(dim=2).values.reshape(-1, 2), dim=0, return_inverse=True)
            m = (slot + count).view(f, 3)  # midpoints of edges ab, bc, ca
            a, b, c = faces.unbind(1)
            mab, mbc, mca = m.unbind(1)
            children = torch.stack(
                [
                    torch.stack([a, mab, mca], 1),
                    torch.stack([mab, b, mbc], 1),
                    torch.stack([mca, mbc, c], 1),
                    torch.stack([mab, mbc, mca], 1),
                ],
                1,
            )  # [F, 4, 3]: children stay next to their parent
            faces = children.reshape(-1, 3)
            midpoints.append(edges)
            count += edges.shape[0]
        return cls(faces, tuple(midpoints))

    def vertex_count(self, coarse: int) -> int:
        """Vertices of the fine mesh made from ``coarse`` vertices: the coarse ones, then the midpoints."""
        return coarse + sum(int(edges.shape[0]) for edges in self.midpoints)

    @property
    def children(self) -> int:
        """Fine faces per coarse face, ``4^L``."""
        return 4 ** len(self.midpoints)

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        for edges in self.midpoints:
            vertices = torch.cat([vertices, 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]])])
        return vertices


def longest_edges(triangles: torch.Tensor) -> torch.Tensor:
    """Index ``k`` of the longest edge ``(v_k, v_{k+1 mod 3})`` of each triangle ``[F, 3, 3]`` → ``[F]`` int64."""
    edges = triangles.roll(-1, dims=1) - triangles
    return torch.linalg.norm(edges, dim=2).argmax(1)


def face_frames(vertices: torch.Tensor, faces: torch.Tensor, edge: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Barycentres ``[F, 3]`` and rotations ``[F, 3, 3]`` (columns x, y, z) of the faces' local frames (§3.1).

    x runs along edge ``edge[f]`` (fixed at the first frame), z along the unit face normal, ``y = z × x``.
    """
    tri = vertices[faces.long()]
    centre = tri.mean(1)
    index = edge[:, None, None].expand(-1, 1, 3)
    start = tri.gather(1, index)[:, 0]
    end = tri.gather(1, ((edge + 1) % 3)[:, None, None].expand(-1, 1, 3))[:, 0]
    x = torch.nn.functional.normalize(end - start, dim=1)
    z = torch.nn.functional.normalize(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    y = torch.linalg.cross(z, x)
    return centre, torch.stack([x, y, z], dim=2)


def project_gaussians(
    means: torch.Tensor,
    rotations: torch.Tensor,
    scales: torch.Tensor,
    world_to_camera: torch.Tensor,
    intrinsics: tuple[float, float, float, float] | torch.Tensor,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection of 3D Gaussians into every view.

    Args:
        means: ``[N, 3]`` centres, m.
        rotations: ``[N, 3, 3]`` rotations (columns are the principal axes).
        scales: ``[N, 3]`` standard deviations along those axes, m.
        world_to_camera: ``[C, 4, 4]`` OpenGL-convention view matrices (the camera looks along −z).
        intrinsics: ``(fx, fy, cx, cy)`` px shared by every view, or a ``[C, 4]`` tensor of one such row per view
            (e.g. :attr:`physavatar.capture.CameraRig.intrinsics`; any dtype and device, used in those of
            ``means``); the image's y axis points down.
        width, height: image size, px (for the radii's culling only).

    Returns:
        ``means2d [C, N, 2]`` px, ``conics [C, N, 3]`` (a, b, c) of the inverse 2D covariance, px⁻²,
        ``depths [C, N]`` m, ``radii [C, N]`` int32 (3σ of the larger eigenvalue; 0 when culled: behind the near
        plane or wholly off screen).

    Raises:
        ValueError: ``intrinsics`` is neither four numbers nor a ``[C, 4]`` tensor.
    """
    fx, fy, cx, cy = _view_intrinsics(intrinsics, world_to_camera.shape[0], means)
    w2c = world_to_camera.to(means)
    rot, t = w2c[:, :3, :3], w2c[:, :3, 3]
    p = torch.einsum("cij,nj->cni", rot, means) + t[:, None]  # [C, N, 3]
    depth = -p[..., 2]
    d = depth.clamp_min(_NEAR)
    u = fx * p[..., 0] / d + cx
    v = -fy * p[..., 1] / d + cy
    # Jacobian of (u, v) with respect to camera coordinates, at the mean. `f * d.reciprocal()` is what `f / d` does
    # for a float f: shared and per-view intrinsics go through one arithmetic.
    zero = torch.zeros_like(d)
    jac = torch.stack(
        [
            torch.stack([fx * d.reciprocal(), zero, fx * p[..., 0] / (d * d)], -1),
            torch.stack([zero, -fy * d.reciprocal(), -fy * p[..., 1] / (d * d)], -1),
        ],
        -2,
    )  # [C, N, 2, 3]
    m = rotations * scales[:, None, :]  # R S
    cov = m @ m.transpose(1, 2)  # [N, 3, 3]
    jw = jac @ rot[:, None]  # [C, N, 2, 3]
    cov2 = jw @ cov[None] @ jw.transpose(-1, -2)
    a = cov2[..., 0, 0] + _LOW_PASS
    b = cov2[..., 0, 1]
    c = cov2[..., 1, 1] + _LOW_PASS
    det = (a * c - b * b).clamp_min(1e-12)
    conics = torch.stack([c / det, -b / det, a / det], -1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
    radius = torch.ceil(3.0 * torch.sqrt(lam)).detach()
    visible = (depth > _NEAR) & (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    return torch.stack([u, v], -1), conics, depth, radii


def _view_intrinsics(intrinsics, views: int, like: torch.Tensor):
    """``(fx, fy, cx, cy)`` px: four floats shared by every view, or four ``[C, 1]`` columns of a ``[C, 4]`` tensor
    in the dtype and device of ``like`` (so that they broadcast against ``[C, N]`` per-view values)."""
    if isinstance(intrinsics, torch.Tensor):
        if tuple(intrinsics.shape) != (views, 4):
            raise ValueError(
                f"intrinsics must be a [{views}, 4] tensor (fx, fy, cx, cy per view) for {views} views, got "
                f"{tuple(intrinsics.shape)}; pass CameraRig.intrinsics or four floats shared by every view"
            )
        return intrinsics.to(like)[:, :, None].unbind(1)
    try:
        fx, fy, cx, cy = (float(value) for value in intrinsics)
    except (TypeError, ValueError, RuntimeError) as error:
        raise ValueError(
            f"intrinsics must be four floats (fx, fy, cx, cy) px or a [{views}, 4] tensor, got {intrinsics!r}; "
            "pass CameraRig.intrinsics for per-camera values"
        ) from error
    return fx, fy, cx, cy


def render_mesh_gaussians(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    appearance: GaussianAppearance,
    world_to_camera: torch.Tensor,
    intrinsics: tuple[float, float, float, float] | torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render a mesh's face-aligned Gaussians into every view.

    Args:
        vertices: ``[V, 3]`` vertices, m (any float dtype; gradients flow to them).
        faces: ``[F, 3]`` triangles.
        appearance: the Gaussians' colours, scales, opacities and frame edges.
        world_to_camera, intrinsics, width, height: the cameras (:func:`project_gaussians`).
        background: ``[3]`` colour behind everything (default black).

    Returns:
        ``image [C, H, W, 3]`` and ``alpha [C, H, W]``, float32.
    """
    centre, rotation = face_frames(vertices, faces, appearance.edge)
    thin = torch.full_like(appearance.log_scales[:, :1], appearance.normal_scale)
    scales = torch.cat([appearance.log_scales.exp(), thin], 1).to(centre)
    means2d, conics, depths, radii = project_gaussians(
        centre, rotation, scales, world_to_camera, intrinsics, width, height
    )
    views = means2d.shape[0]
    colors = appearance.colors.clamp(0.0, 1.0).float()[None].expand(views, -1, -1)
    opacity = torch.sigmoid(appearance.opacity_logits).float()[None].expand(views, -1)
    return rasterize_gaussians(
        means2d.float().contiguous(),
        conics.float().contiguous(),
        colors.contiguous(),
        opacity.contiguous(),
        depths.float().contiguous(),
        radii.contiguous(),
        width,
        height,
        background=background,
        near=_NEAR,
    )


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, weight_l1: float = 0.8, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Eq. 1: ``λ ‖I − Î‖₁ + (1 − λ)(1 − SSIM(I, Î))`` over a batch of ``[C, H, W, 3]`` images (mean L1).

    The paper writes ``(1 − λ)·SSIM``; as in 3DGS and Dynamic 3D Gaussians, whose loss it cites, the term
    minimised is the dissimilarity ``1 − SSIM``. ``λ = 0.8`` as there.

    With ``weights`` ``[C, H, W]`` (e.g. a garment mask), both terms are weighted means over the pixels: the L1 of
    each pixel, and the SSIM of the 11×11 window centred on it (pixels within 5 of the border, where no window
    fits, weigh nothing in the SSIM term). Pixels of zero weight farther than 5 px from any weighted one do not
    change the loss.
    """
    if weights is None:
        l1 = (image - target).abs().mean()
        return weight_l1 * l1 + (1.0 - weight_l1) * (1.0 - ssim(image, target, compute_dtype=torch.float32))
    if weights.shape != image.shape[:-1]:
        raise ValueError(f"weights {tuple(weights.shape)} must be one per pixel of the images {tuple(image.shape)}")
    weights = weights.to(image.dtype)
    l1 = ((image - target).abs().mean(-1) * weights).sum() / weights.sum().clamp_min(1e-12)
    similarity = ssim_map(image, target, compute_dtype=torch.float32).mean(-1)
    pad_y = (image.shape[-3] - similarity.shape[-2]) // 2
    pad_x = (image.shape[-2] - similarity.shape[-1]) // 2
    inner = weights[:, pad_y : pad_y + similarity.shape[-2], pad_x : pad_x + similarity.shape[-1]]
    ssim_term = (similarity.to(image.dtype) * inner).sum() / inner.sum().clamp_min(1e-12)
    return weight_l1 * l1 + (1.0 - weight_l1) * (1.0 - ssim_term)
