"""Scripted experiments as TOML scenarios, as a library: the schema and its checks, the runs a scenario makes, and
the offline render that writes its frames and metrics.

A scenario names the scene, material, discretisation, solver settings, pins, keyframed drags, timed forces, cuts,
colliders (a plane may move along keyframes), cameras (orbit or fixed), outputs and what its run must show
(``[expect]``); optional ``[[variants]]`` override the material, the discretisation or the expectations, and a
``[nerf]`` table fits a NeRF to render warped (PIE-NeRF §4.6). The format and the files written are described in
:mod:`apps.render`.

Modules: :mod:`~pienerf.scenario.schema` (:func:`load_scenario`, the checks, the tables' values),
:mod:`~pienerf.scenario.keyframes`, :mod:`~pienerf.scenario.cameras`, :mod:`~pienerf.scenario.colliders`,
:mod:`~pienerf.scenario.nerf` (:func:`prepare_nerf`), :mod:`~pienerf.scenario.runs` (:func:`build_runs`,
:func:`advance`, the metrics), :mod:`~pienerf.scenario.expectations` (:func:`check_expectations`) and
:mod:`~pienerf.scenario.runner` (:func:`render_scenario`) and :mod:`~pienerf.scenario.sweep` (:func:`run_sweep`: the
points of a ``[sweep]`` table, each rendered by the executor of :mod:`pienerf.executor`).

A scripted figure is not an interactive frame: its steps iterate to the solver's tolerance
(:data:`OFFLINE_NEWTON_ITERATIONS` at most), where the viewer takes one Newton iteration.
"""

from pienerf.scenario.cameras import scenario_cameras
from pienerf.scenario.colliders import scenario_colliders
from pienerf.scenario.expectations import EXPECT_KEYS, check_expectations, failed_lines
from pienerf.scenario.keyframes import keyframe
from pienerf.scenario.nerf import ScenarioNerf, nerf_fit, prepare_nerf, progress_log
from pienerf.scenario.runner import (
    MODE_LABELS,
    OWNED_FILES,
    clear_earlier_render,
    failure_summary,
    label_tile,
    render_scenario,
    save_png,
)
from pienerf.scenario.runs import (
    OFFLINE_NEWTON_ITERATIONS,
    ScenarioRun,
    StepTally,
    advance,
    apply_controls,
    build_run,
    build_runs,
    measure_warp_error,
    merged_breakdown,
    run_metrics,
    sample_volumes,
    warp_error_summary,
)
from pienerf.scenario.schema import (
    MAX_COORDINATE,
    MAX_FRAMES,
    MAX_STEPS,
    MAX_SWEEP_POINTS,
    MAX_TIME,
    NERF_WARPS,
    OUTPUT_DEFAULTS,
    SWEEP_MODES,
    ScenarioError,
    apply_sweep_point,
    frame_count,
    load_scenario,
    require_video_encoder,
    scenario_outputs,
    sweep_points,
    unmet_requirement,
    volume_sample_frames,
)
from pienerf.scenario.sweep import CONTACT_SHEET, SWEEP_INDEX, contact_sheet, point_summary, render_point, run_sweep

__all__ = [
    "CONTACT_SHEET",
    "EXPECT_KEYS",
    "MAX_COORDINATE",
    "MAX_FRAMES",
    "MAX_STEPS",
    "MAX_SWEEP_POINTS",
    "MAX_TIME",
    "MODE_LABELS",
    "NERF_WARPS",
    "OFFLINE_NEWTON_ITERATIONS",
    "OUTPUT_DEFAULTS",
    "OWNED_FILES",
    "SWEEP_INDEX",
    "SWEEP_MODES",
    "ScenarioError",
    "ScenarioNerf",
    "ScenarioRun",
    "StepTally",
    "advance",
    "apply_controls",
    "apply_sweep_point",
    "build_run",
    "build_runs",
    "check_expectations",
    "clear_earlier_render",
    "contact_sheet",
    "failed_lines",
    "failure_summary",
    "frame_count",
    "keyframe",
    "label_tile",
    "load_scenario",
    "measure_warp_error",
    "merged_breakdown",
    "nerf_fit",
    "point_summary",
    "prepare_nerf",
    "progress_log",
    "render_point",
    "render_scenario",
    "save_png",
    "require_video_encoder",
    "run_metrics",
    "run_sweep",
    "sample_volumes",
    "scenario_cameras",
    "scenario_colliders",
    "scenario_outputs",
    "sweep_points",
    "unmet_requirement",
    "volume_sample_frames",
    "warp_error_summary",
]
