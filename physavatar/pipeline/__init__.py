"""PhysAvatar end to end: on a synthetic capture (capture → track → estimate → appearance → animate → evaluate) or on
a user's own capture folder (prepare → track → ... → evaluate, no truth needed).

- :mod:`~physavatar.pipeline.stages`: the stages, their settings and output folders, and :func:`run`;
- :mod:`~physavatar.pipeline.user_capture`: the stages that differ on a user's capture, and :func:`run_capture`;
- :mod:`~physavatar.pipeline.export`: the synthetic capture written as a user's capture folder, with defects;
- :mod:`~physavatar.pipeline.batch`: the stages over many capture folders or a synthetic study (garments × motions
  × fabrics), one point at a time, and the batch's summary plot;
- :mod:`~physavatar.pipeline.report`: what the stages write for people to read: the markdown report, its plots and
  image strips.
"""

from physavatar.pipeline.batch import (
    BATCH_INDEX,
    BATCH_SUMMARY,
    STUDY_GARMENTS,
    capture_points,
    parse_fabric,
    plot_batch_summary,
    point_metrics,
    run_batch_point,
    study_points,
)
from physavatar.pipeline.export import export_capture_folder
from physavatar.pipeline.report import SMOKE_NOTE, plot_estimation, plot_report, report_markdown, write_strip
from physavatar.pipeline.stages import (
    COARSE_MESH_TRACKING,
    FITS,
    OUTPUTS,
    STAGES,
    PipelineConfig,
    PipelineInterrupted,
    StageInputs,
    animate,
    appearance,
    camera_views,
    capture,
    estimate,
    evaluate,
    run,
    stage_inputs,
    stderr_progress,
    track_stage,
)
from physavatar.pipeline.user_capture import (
    CAPTURE_OUTPUTS,
    CAPTURE_STAGES,
    animate_capture,
    evaluate_capture,
    prepare,
    run_capture,
)

__all__ = [
    "BATCH_INDEX",
    "BATCH_SUMMARY",
    "CAPTURE_OUTPUTS",
    "CAPTURE_STAGES",
    "COARSE_MESH_TRACKING",
    "FITS",
    "OUTPUTS",
    "SMOKE_NOTE",
    "STAGES",
    "STUDY_GARMENTS",
    "PipelineConfig",
    "PipelineInterrupted",
    "StageInputs",
    "animate",
    "animate_capture",
    "appearance",
    "capture",
    "estimate",
    "evaluate",
    "evaluate_capture",
    "export_capture_folder",
    "camera_views",
    "capture_points",
    "parse_fabric",
    "plot_batch_summary",
    "point_metrics",
    "plot_estimation",
    "plot_report",
    "prepare",
    "report_markdown",
    "run",
    "run_batch_point",
    "run_capture",
    "stage_inputs",
    "stderr_progress",
    "study_points",
    "track_stage",
    "write_strip",
]
