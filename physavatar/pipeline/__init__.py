"""PhysAvatar end to end on a synthetic capture: capture → track → estimate → appearance → animate → evaluate.

- :mod:`~physavatar.pipeline.stages`: the stages, their settings and output folders, and :func:`run`;
- :mod:`~physavatar.pipeline.report`: what the stages write for people to read: the markdown report, its plots and
  image strips.
"""

from physavatar.pipeline.report import SMOKE_NOTE, plot_estimation, plot_report, report_markdown, write_strip
from physavatar.pipeline.stages import (
    COARSE_MESH_TRACKING,
    OUTPUTS,
    STAGES,
    PipelineConfig,
    PipelineInterrupted,
    animate,
    appearance,
    capture,
    estimate,
    evaluate,
    run,
    stderr_progress,
    track_stage,
)

__all__ = [
    "COARSE_MESH_TRACKING",
    "OUTPUTS",
    "SMOKE_NOTE",
    "STAGES",
    "PipelineConfig",
    "PipelineInterrupted",
    "animate",
    "appearance",
    "capture",
    "estimate",
    "evaluate",
    "plot_estimation",
    "plot_report",
    "report_markdown",
    "run",
    "stderr_progress",
    "track_stage",
    "write_strip",
]
