"""Rendering a simulated body: quadratic ray warping of the NeRF (Eq. 19–21), the previews a viewer shows, the
resolution schedule that keeps them inside a frame budget, mesh refinement and the warp-error probe (Fig. 8)."""

from pienerf.render.deformed import (
    LIGHT_DIRECTION,
    MODES,
    DeformedFrame,
    DeformedRenderer,
    GroundPlane,
    RenderStats,
    bucket_size,
)
from pienerf.render.mesh_refine import MAX_REFINED_VERTICES, split_long_edges
from pienerf.render.previews import (
    Frame,
    MeshRenderBackend,
    NerfRenderBackend,
    ParticleRenderBackend,
    RenderBackend,
    ViewRays,
)
from pienerf.render.refinement import RefinementSchedule
from pienerf.render.warp_error import SILHOUETTE_ALPHA, RegionError, WarpErrorProbe, region_error, region_mask

__all__ = [
    "DeformedFrame",
    "DeformedRenderer",
    "Frame",
    "GroundPlane",
    "LIGHT_DIRECTION",
    "MAX_REFINED_VERTICES",
    "MODES",
    "MeshRenderBackend",
    "NerfRenderBackend",
    "ParticleRenderBackend",
    "RefinementSchedule",
    "RegionError",
    "RenderBackend",
    "RenderStats",
    "SILHOUETTE_ALPHA",
    "ViewRays",
    "WarpErrorProbe",
    "bucket_size",
    "region_error",
    "region_mask",
    "split_long_edges",
]
