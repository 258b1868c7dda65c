"""Evaluation of animated garments against the truth (PhysAvatar §4, Table 2).

Geometry: the mean Chamfer distance and the F-score at ``τ = 1 mm`` (the paper's ``τ = 0.001``) between the
garment surfaces of every frame. Both are computed from point-to-*surface* distances: points sampled uniformly by
area on one mesh, their exact distance to the other mesh through its BVH (:meth:`kernels.raycast.MeshBVH.closest`).
Point-to-point distances between two samplings would add the sampling's own spacing (millimetres on a garment),
which would swamp a 1 mm threshold.

* Chamfer distance ``CD = mean_{p∈P} d(p, G)² + mean_{g∈G} d(g, P)²``, m², as in Fan et al. 2017 (the paper's [73]).
* F-score ``F = 2 P R / (P + R)`` with precision ``P = mean_{p∈P} [d(p, G) < τ]`` and recall
  ``R = mean_{g∈G} [d(g, P) < τ]`` (Knapitsch et al. 2017, the paper's [104]).

Appearance: PSNR and SSIM (:mod:`kernels.image_metrics`) of renders against renders of the truth.

The baseline "LBS" moves every garment vertex with the skinning of its nearest body point, as the boundary
vertices move (Appendix A.3.2): what a garment without dynamics does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.body import Body
from physavatar.garment import boundary_targets

__all__ = ["GeometryScores", "chamfer_fscore", "geometry_scores", "lbs_garment", "surface_samples"]

F_SCORE_TAU = 1e-3  # m


def surface_samples(vertices: torch.Tensor, faces: torch.Tensor, count: int, seed: int = 0) -> torch.Tensor:
    """``count`` points ``[count, 3]`` uniformly distributed over the mesh's area (deterministic for a seed)."""
    tri = vertices.to(torch.float64)[faces.long()]
    area = 0.5 * torch.linalg.norm(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    generator = torch.Generator().manual_seed(seed)
    face = torch.multinomial(area.cpu(), count, replacement=True, generator=generator).to(vertices.device)
    r1, r2 = torch.rand(2, count, 1, generator=generator, dtype=torch.float64).to(vertices.device)
    s = r1.sqrt()
    t = tri[face]
    return (1.0 - s) * t[:, 0] + s * (1.0 - r2) * t[:, 1] + s * r2 * t[:, 2]


def chamfer_fscore(
    prediction: torch.Tensor,
    truth: torch.Tensor,
    faces: torch.Tensor,
    truth_faces: torch.Tensor | None = None,
    tau: float = F_SCORE_TAU,
    samples: int = 20000,
    seed: int = 0,
) -> tuple[float, float]:
    """Chamfer distance (m²) and F-score at ``tau`` (m) between two meshes (module docstring).

    Args:
        prediction: ``[V, 3]`` predicted vertices, m.
        truth: ``[V′, 3]`` true vertices, m.
        faces: ``[F, 3]`` the prediction's triangles.
        truth_faces: the truth's triangles (default: ``faces``).
        tau: F-score threshold, m.
        samples: points sampled on each surface.
        seed: sampling seed (the same points for every method compared).
    """
    truth_faces = faces if truth_faces is None else truth_faces
    device = backend.torch_device()
    prediction, truth = prediction.to(device), truth.to(device)
    faces, truth_faces = faces.to(device), truth_faces.to(device)
    p_points = surface_samples(prediction, faces, samples, seed)
    g_points = surface_samples(truth, truth_faces, samples, seed + 1)
    d_pg = MeshBVH(truth.float(), truth_faces).closest(p_points.float()).distance.double()
    d_gp = MeshBVH(prediction.float(), faces).closest(g_points.float()).distance.double()
    chamfer = float((d_pg**2).mean() + (d_gp**2).mean())
    precision = float((d_pg < tau).double().mean())
    recall = float((d_gp < tau).double().mean())
    fscore = 0.0 if precision + recall == 0.0 else 2.0 * precision * recall / (precision + recall)
    return chamfer, fscore


@dataclass
class GeometryScores:
    """Per-frame and mean geometry scores of one method.

    Attributes:
        chamfer: ``[T]`` Chamfer distance per frame, m².
        fscore: ``[T]`` F-score per frame.
        vertex_error: ``[T]`` mean vertex distance to the truth, m (same topology as the truth).
    """

    chamfer: torch.Tensor
    fscore: torch.Tensor
    vertex_error: torch.Tensor
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Means over frames: ``chamfer`` (m²), ``fscore``, ``vertex_error`` (m)."""
        return {
            "chamfer": float(self.chamfer.mean()),
            "fscore": float(self.fscore.mean()),
            "vertex_error": float(self.vertex_error.mean()),
            **self.extra,
        }


def geometry_scores(
    prediction: torch.Tensor, truth: torch.Tensor, faces: torch.Tensor, tau: float = F_SCORE_TAU, samples: int = 20000
) -> GeometryScores:
    """Scores of a garment sequence ``[T, V, 3]`` against the true one (same topology), frame by frame.

    Raises:
        ValueError: the sequences differ in frame or vertex count.
    """
    if prediction.shape != truth.shape or prediction.dim() != 3:
        raise ValueError(
            f"prediction {tuple(prediction.shape)} and truth {tuple(truth.shape)} must both be [T, V, 3] with the "
            "same frames and vertices; evaluate sequences of the same garment over the same motion"
        )
    chamfer, fscore = [], []
    for t in range(prediction.shape[0]):
        c, f = chamfer_fscore(prediction[t], truth[t], faces, tau=tau, samples=samples, seed=t)
        chamfer.append(c)
        fscore.append(f)
    error = torch.linalg.norm(prediction.double() - truth.double(), dim=2).mean(1).cpu()
    return GeometryScores(torch.tensor(chamfer), torch.tensor(fscore), error)


def lbs_garment(
    body: Body, rest_vertices: torch.Tensor, rotations: torch.Tensor, root_translation: torch.Tensor | None = None
) -> torch.Tensor:
    """The "LBS" baseline: every garment vertex skinned by its nearest body point's weights, ``[T, V, 3]``, m."""
    return boundary_targets(body, rest_vertices.to(torch.float64), rotations, root_translation)
