"""Fitting the garment to the capture: its tracked geometry, its physics and its appearance, and their scores.

The paper's §3.1–§3.3 and its evaluation, each a module:

- :mod:`~physavatar.fit.gaussians`: Gaussians glued to mesh faces and their rasterised images (§3.1, Eq. 1);
- :mod:`~physavatar.fit.tracking`: the garment mesh tracked through the capture (§3.1, Eqs. 1–4);
- :mod:`~physavatar.fit.estimation`: the fabric's physical parameters from the tracked meshes (§3.2, Algorithm 1);
- :mod:`~physavatar.fit.regions`: stiffness per garment region, fitted through the rollout's adjoint;
- :mod:`~physavatar.fit.images`: the stiffness fitted to the capture's images through the rollout, no tracked mesh;
- :mod:`~physavatar.fit.appearance`: the garment's albedo and the light by inverse rendering (§3.3, Eq. 8);
- :mod:`~physavatar.fit.evaluation`: geometry scores against the truth (Chamfer distance, F-score; Table 2).

Both :mod:`~physavatar.fit.gaussians` and :mod:`~physavatar.fit.appearance` define an image loss; the package
exports the Gaussians' as ``photometric_loss`` (Eq. 1) and the albedo's as ``albedo_loss`` (Eq. 8).
"""

from physavatar.fit.appearance import (
    Appearance,
    GarmentPixels,
    albedo_error,
    albedo_loss,
    baked_face_colors,
    estimate_appearance,
    gather_garment_pixels,
    relight,
    render_pixels,
)
from physavatar.fit.estimation import (
    FD_STEPS,
    SYNTHETIC_FABRIC,
    EstimationProblem,
    EstimationResult,
    FabricParameters,
    IterationRecord,
    Rollout,
    estimate_analytic,
    estimate_finite_differences,
    rollout,
    sim_loss,
)
from physavatar.fit.evaluation import GeometryScores, chamfer_fscore, geometry_scores, lbs_garment, surface_samples
from physavatar.fit.gaussians import (
    GaussianAppearance,
    Subdivision,
    face_frames,
    longest_edges,
    photometric_loss,
    project_gaussians,
    render_mesh_gaussians,
)
from physavatar.fit.images import ImageEstimate, ImageFitConfig, estimate_images, image_loss
from physavatar.fit.regions import RegionEstimate, check_regions, estimate_regions, garment_regions
from physavatar.fit.tracking import (
    AvatarGaussians,
    TrackConfig,
    TrackResult,
    fit_first_frame,
    isometry_loss,
    mesh_neighbours,
    normal_loss,
    track,
)

__all__ = [
    "FD_STEPS",
    "SYNTHETIC_FABRIC",
    "Appearance",
    "AvatarGaussians",
    "EstimationProblem",
    "EstimationResult",
    "FabricParameters",
    "GarmentPixels",
    "GaussianAppearance",
    "GeometryScores",
    "ImageEstimate",
    "ImageFitConfig",
    "IterationRecord",
    "RegionEstimate",
    "Rollout",
    "Subdivision",
    "TrackConfig",
    "TrackResult",
    "albedo_error",
    "albedo_loss",
    "baked_face_colors",
    "chamfer_fscore",
    "check_regions",
    "estimate_analytic",
    "estimate_appearance",
    "estimate_finite_differences",
    "estimate_images",
    "estimate_regions",
    "face_frames",
    "fit_first_frame",
    "gather_garment_pixels",
    "garment_regions",
    "geometry_scores",
    "image_loss",
    "isometry_loss",
    "lbs_garment",
    "longest_edges",
    "mesh_neighbours",
    "normal_loss",
    "photometric_loss",
    "project_gaussians",
    "relight",
    "render_mesh_gaussians",
    "render_pixels",
    "rollout",
    "sim_loss",
    "surface_samples",
    "track",
]
