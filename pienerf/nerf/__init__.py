"""The NeRF (PIE-NeRF §3.1): cameras, multi-view datasets, the instant-NGP field and its trainer, fitting and
caching a NeRF to a scene's views, and the trained NeRF as a solid the simulator samples (§4.1)."""

from pienerf.nerf.cameras import (
    Cameras,
    check_downscale,
    look_at_cameras,
    orbit_cameras,
    pinhole_camera,
    quaternion_matrix,
    view_index,
    viser_cameras,
)
from pienerf.nerf.datasets import MAX_IMAGE_PIXELS, NerfDataset, load_nerf_dataset
from pienerf.nerf.field import (
    InferenceMLP,
    NerfDensity,
    NGPConfig,
    NGPField,
    OccupancyGrid,
    render_rays,
    spherical_harmonics,
    truncated_exp,
)
from pienerf.nerf.fitting import Z_UP_TO_Y_UP, NerfFit, dataset_nerf, dataset_nerf_path, fit_nerf, visual_hull
from pienerf.nerf.solid import NerfSceneDensity, nerf_proxy_mesh
from pienerf.nerf.training import (
    CHECKPOINT_FORMAT,
    NerfCheckpoint,
    TrainConfig,
    Trainer,
    load_checkpoint,
    save_checkpoint,
    start_optimizer_import,
)
from pienerf.nerf.training_curve import (
    ERROR_FULL_SCALE,
    CurvePoint,
    TrainingCurve,
    error_heat_map,
    error_panel,
    train_curve,
    write_error_images,
)

__all__ = [
    "CHECKPOINT_FORMAT",
    "Cameras",
    "CurvePoint",
    "ERROR_FULL_SCALE",
    "InferenceMLP",
    "MAX_IMAGE_PIXELS",
    "NGPConfig",
    "NGPField",
    "NerfCheckpoint",
    "NerfDataset",
    "NerfDensity",
    "NerfFit",
    "NerfSceneDensity",
    "OccupancyGrid",
    "TrainConfig",
    "Trainer",
    "TrainingCurve",
    "Z_UP_TO_Y_UP",
    "check_downscale",
    "dataset_nerf",
    "dataset_nerf_path",
    "error_heat_map",
    "error_panel",
    "fit_nerf",
    "load_checkpoint",
    "load_nerf_dataset",
    "look_at_cameras",
    "nerf_proxy_mesh",
    "orbit_cameras",
    "pinhole_camera",
    "quaternion_matrix",
    "render_rays",
    "save_checkpoint",
    "spherical_harmonics",
    "start_optimizer_import",
    "train_curve",
    "truncated_exp",
    "view_index",
    "viser_cameras",
    "visual_hull",
    "write_error_images",
]
