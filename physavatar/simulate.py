"""A garment simulated on a moving body, and the files that record it (PhysAvatar §3.2, Eq. 5; Appendix A.3).

Each frame is one implicit step of :class:`~physavatar.cloth.SolverCloth` at ``Δt = 1 / fps`` (the paper: 0.04 s,
25 fps): ``V^g_{t+1} = f(V^g_t, V̇^g_t, V^b_{t+1}, V^C_{t+1}, ρ, κ_s, κ_b, Δt)`` (Eq. 5), with the body collider
moving from its frame-``t`` pose to its frame-``t+1`` pose within the step and the boundary vertices ``V^b``
following the LBS of their nearest body points (Appendix A.3.2).

Writers: one NPZ with both sequences and faces, optional per-frame OBJ/PLY meshes, an MP4 of the dressed
mannequin from an orbiting camera (ray cast by :func:`kernels.raycast.shade`, with the shadow on a ground plane)
and a JSON of per-step statistics. Each writes every file through a ``staging`` step passed in
(:data:`physavatar.result_files.Staging`): ``staging(path)`` is a context manager that yields the file to write for
``path`` and puts it at ``path`` once its block ends cleanly. The default writes ``path`` itself; a program passes one
that writes a temporary file and moves it into place (``pienerf.output_files.atomic_path``), so that an interrupted
write leaves no half-written file.

Ctrl-C during :func:`simulate` raises :class:`SimulationInterrupted`, a ``KeyboardInterrupt`` that carries the
frames finished so far.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from kernels import backend
from kernels.raycast import MeshBVH, shade
from physavatar.body import Body, Motion
from physavatar.cloth import ClothConfig, ClothStepReport, SolverCloth
from physavatar.drive import BodyDriver
from physavatar.garment import Garment, select_boundary
from physavatar.result_files import Staging, write_arrays, write_json

__all__ = [
    "SimulationInterrupted",
    "SimulationResult",
    "Staging",
    "render_video",
    "require_video_encoder",
    "simulate",
    "stalled_steps",
    "write_meshes",
    "write_npz",
    "write_stats_json",
]

GARMENT_COLOR = (0.80, 0.22, 0.20)
BODY_COLOR = (0.78, 0.74, 0.68)
GROUND_COLOR = (0.92, 0.92, 0.90)
SKY_COLOR = (1.0, 1.0, 1.0)


@dataclass
class SimulationResult:
    """A simulated sequence.

    Attributes:
        garment_frames: ``[T, V, 3]`` garment vertices per frame (frame 0 is the start), m.
        body_frames: ``[T, B, 3]`` body vertices per frame, m.
        garment_faces: ``[F, 3]`` int64.
        body_faces: ``[Fb, 3]`` int64.
        boundary_index: ``[D]`` int64 Dirichlet garment vertices.
        fps: frames per second (``Δt = 1 / fps``).
        stats: one :class:`~physavatar.cloth.ClothStepReport` per step (``T − 1`` of them).
        wall_time: seconds each step took.
    """

    garment_frames: torch.Tensor
    body_frames: torch.Tensor
    garment_faces: torch.Tensor
    body_faces: torch.Tensor
    boundary_index: torch.Tensor
    fps: float
    stats: list[ClothStepReport]
    wall_time: list[float]


class SimulationInterrupted(KeyboardInterrupt):
    """Ctrl-C (``KeyboardInterrupt``) during :func:`simulate`, with the frames finished before it.

    Attributes:
        result: :class:`SimulationResult` of the start frame and the steps that finished (``len(result.stats)``
            of them; none if the first step did not finish).
        frames: steps that were asked for.
    """

    def __init__(self, result: SimulationResult, frames: int):
        super().__init__(f"interrupted after {len(result.stats)} of {frames} steps")
        self.result, self.frames = result, frames


def simulate(
    garment: Garment,
    body: Body,
    motion: Motion,
    config: ClothConfig | None = None,
    frames: int | None = None,
    device: str | None = None,
    progress: bool | Callable[[int, ClothStepReport], None] = True,
    boundary: torch.Tensor | None = None,
) -> SimulationResult:
    """Simulate ``garment`` on ``body`` moving through ``motion``, one implicit step per motion frame (Eq. 5).

    Args:
        garment: placed outside the body in the motion's first pose (:func:`physavatar.garment.place_on_body`).
        body: the skinned body.
        motion: poses; must start at the pose the garment was placed on and hold at least ``frames + 1`` frames.
        config: cloth material and solver settings (default: cotton, :class:`ClothConfig`).
        frames: steps to simulate; ``None`` simulates the whole motion.
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the backend's device or picks the default.
        progress: ``True`` writes one line per step to stderr; a callable receives ``(step, stats)``.
        boundary: ``[D]`` Dirichlet vertices; ``None`` selects them with ``select_boundary(mode="auto")``.

    Returns:
        :class:`SimulationResult` with ``T = frames + 1`` frames.

    Raises:
        ValueError: too few motion frames, or a step that produced NaN.
        SimulationInterrupted: on Ctrl-C during the steps, with the frames finished before it.
    """
    device = backend.init(device)
    config = config or ClothConfig()
    frames = motion.num_frames - 1 if frames is None else int(frames)
    BodyDriver.check_steps(motion, frames)
    boundary = select_boundary(garment, body) if boundary is None else boundary.long().cpu()
    driver = BodyDriver.from_motion(body, motion, garment.vertices, boundary, frames)
    dt = driver.dt

    solver = SolverCloth(garment.vertices, garment.faces, config, body.faces)
    state, spare = solver.initial_state(), solver.initial_state()  # double-buffered: each step writes the other
    out = [state.x.clone()]
    on_device = driver.to(backend.torch_device())
    stats, wall = [], []

    def finished() -> SimulationResult:
        """The frames of the steps that finished (a step counts once its positions are kept)."""
        done = len(out) - 1
        return SimulationResult(
            torch.stack(out).cpu(),
            driver.body_frames[: done + 1].cpu(),
            garment.faces.long().cpu(),
            body.faces.long().cpu(),
            boundary.cpu(),
            float(motion.fps),
            stats[:done],
            wall[:done],
        )

    try:
        for t in range(frames):
            control = on_device.control(t)
            start = time.perf_counter()
            step = solver.step(state, spare, control, dt)
            wall.append(time.perf_counter() - start)
            state, spare = spare, state
            if not bool(torch.isfinite(state.x).all()):
                raise ValueError(f"step {t + 1} produced NaN or inf positions; lower Δt or check the inputs")
            stats.append(step)
            out.append(state.x.clone())
            if callable(progress):
                progress(t + 1, step)
            elif progress:
                print(
                    f"step {t + 1}/{frames}: {step.newton_iterations} Newton iterations, "
                    f"min distance to body {step.min_distance_body * 1e3:.3f} mm, {wall[-1]:.2f} s",
                    file=sys.stderr,
                )
    except KeyboardInterrupt as stop:
        raise SimulationInterrupted(finished(), frames) from stop
    return finished()


# ---------------------------------------------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------------------------------------------


def write_npz(result: SimulationResult, path: str | Path, staging: Staging = contextlib.nullcontext) -> Path:
    """One NPZ with ``garment_frames [T, V, 3]``, ``body_frames [T, B, 3]`` (m), both face arrays,
    ``boundary_index`` and ``fps``, at ``path`` exactly (no suffix added), written through ``staging``."""
    return write_arrays(
        path,
        staging,
        garment_frames=result.garment_frames.numpy(),
        body_frames=result.body_frames.numpy(),
        garment_faces=result.garment_faces.numpy(),
        body_faces=result.body_faces.numpy(),
        boundary_index=result.boundary_index.numpy(),
        fps=np.float64(result.fps),
    )


def write_meshes(
    result: SimulationResult, folder: str | Path, fmt: str = "obj", staging: Staging = contextlib.nullcontext
) -> list[Path]:
    """Per-frame garment meshes ``garment_0000.<fmt>`` (``fmt``: ``"obj"`` or ``"ply"``) in ``folder``, each
    written through ``staging``: an interrupted run keeps the frames written before it."""
    if fmt not in ("obj", "ply"):
        raise ValueError(f"mesh format must be 'obj' or 'ply', got {fmt!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    faces = result.garment_faces.numpy()
    paths = []
    for t, x in enumerate(result.garment_frames.numpy()):
        path = folder / f"garment_{t:04d}.{fmt}"
        with staging(path) as target:
            trimesh.Trimesh(x, faces, process=False).export(target, file_type=fmt)
        paths.append(path)
    return paths


def stalled_steps(result: SimulationResult) -> int:
    """How many steps ended with a line search that could not move (``ClothStepReport.line_search_stalled``): each left
    the garment where the step's Newton iteration stood, not at a solution of Eq. 5."""
    return sum(s.line_search_stalled for s in result.stats)


def write_stats_json(result: SimulationResult, path: str | Path, staging: Staging = contextlib.nullcontext) -> Path:
    """Per-step statistics as JSON: Newton iterations, convergence, min distances (m), contacts, phase times (s);
    the summary counts the unconverged steps and those whose line search stalled. Written through ``staging``."""
    steps = []
    for t, (s, wall) in enumerate(zip(result.stats, result.wall_time, strict=True)):
        record = dataclasses.asdict(s)
        for key in ("min_distance_body", "min_distance_self"):
            record[key] = None if math.isinf(record[key]) else record[key]
        steps.append({"step": t + 1, "wall_time_s": wall, **record})
    summary = {
        "frames": len(steps),
        "dt_s": 1.0 / result.fps,
        "garment_vertices": int(result.garment_frames.shape[1]),
        "body_vertices": int(result.body_frames.shape[1]),
        "mean_wall_time_s": float(np.mean(result.wall_time)) if steps else 0.0,
        "mean_newton_iterations": float(np.mean([s.newton_iterations for s in result.stats])) if steps else 0.0,
        "min_distance_body_m": min((s.min_distance_body for s in result.stats), default=math.inf),
        "unconverged_steps": sum(not s.converged for s in result.stats),
        "line_search_stalled_steps": stalled_steps(result),
    }
    if math.isinf(summary["min_distance_body_m"]):
        summary["min_distance_body_m"] = None
    return write_json(path, {"summary": summary, "steps": steps}, staging, indent=1)


def require_video_encoder() -> None:
    """Raise ``ModuleNotFoundError``, naming the fix, where :func:`render_video` cannot write an ``.mp4``: imageio
    writes it through the imageio-ffmpeg package (without it, imageio picks another plugin by the file name and fails
    with an unrelated error). Call it before long work whose results include a video."""
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ModuleNotFoundError(
            "writing an .mp4 video needs the imageio-ffmpeg package, which is not installed: pip install imageio-ffmpeg"
        )


def render_video(
    result: SimulationResult,
    path: str | Path,
    size: tuple[int, int] = (480, 360),
    turns: float = 1.0,
    field_of_view: float = 40.0,
    staging: Staging = contextlib.nullcontext,
) -> Path:
    """An MP4 of the dressed body from a camera orbiting it ``turns`` times, one video frame per simulated frame.

    Garment, body and a ground plane are ray cast with :func:`kernels.raycast.shade` (Lambert, one directional
    light, hard shadows, so the ground carries the figure's shadow). The camera looks at the body's centre.

    Args:
        result: the sequence.
        path: ``.mp4`` file (written with imageio-ffmpeg, H.264).
        size: ``(width, height)`` in pixels; multiples of 16 avoid resizing.
        turns: camera revolutions over the sequence.
        field_of_view: vertical field of view, degrees.
        staging: the staging step the file is written through (see the module docstring); keep the ``.mp4`` suffix.
    """
    import imageio.v2 as imageio

    require_video_encoder()
    width, height = size
    device = backend.torch_device()
    garment, body = result.garment_frames, result.body_frames
    v, b = garment.shape[1], body.shape[1]
    span = torch.cat([garment.reshape(-1, 3), body.reshape(-1, 3)])
    lo, hi = span.amin(0), span.amax(0)
    extent = float((hi - lo)[[0, 2]].max()) + 60.0  # reaches the horizon
    ground_y = float(body[:, :, 1].min()) - 1e-3
    cx, cz = 0.5 * float(lo[0] + hi[0]), 0.5 * float(lo[2] + hi[2])
    ground = torch.tensor(
        [
            [cx - extent, ground_y, cz - extent],
            [cx + extent, ground_y, cz - extent],
            [cx + extent, ground_y, cz + extent],
            [cx - extent, ground_y, cz + extent],
        ],
        dtype=torch.float64,
    )
    faces = torch.cat([result.garment_faces, result.body_faces + v, torch.tensor([[0, 3, 2], [0, 2, 1]]) + v + b])
    colors = torch.cat(
        [
            torch.tensor(GARMENT_COLOR).expand(result.garment_faces.shape[0], 3),
            torch.tensor(BODY_COLOR).expand(result.body_faces.shape[0], 3),
            torch.tensor(GROUND_COLOR).expand(2, 3),
        ]
    ).to(device)

    def scene(t: int) -> torch.Tensor:
        return torch.cat([garment[t], body[t], ground]).to(device, torch.float32)

    bvh = MeshBVH(scene(0), faces.to(device))
    frames = garment.shape[0]
    j, i = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    tan = math.tan(math.radians(field_of_view) / 2.0)
    px = ((i + 0.5) / width * 2.0 - 1.0) * tan * width / height
    py = (1.0 - (j + 0.5) / height * 2.0) * tan
    sky = torch.tensor(SKY_COLOR, device=device)
    with staging(Path(path)) as staged:
        writer = imageio.get_writer(staged, fps=result.fps, codec="libx264", quality=7, macro_block_size=16)
        try:
            for t in range(frames):
                if t:
                    bvh.refit(scene(t))
                target = body[t].mean(0).to(device, torch.float32)
                angle = 2.0 * math.pi * turns * t / max(frames, 1)
                eye = target + torch.tensor([3.2 * math.sin(angle), 0.5, 3.2 * math.cos(angle)], device=device)
                forward = torch.nn.functional.normalize(target - eye, dim=0)
                right = torch.nn.functional.normalize(
                    torch.linalg.cross(forward, torch.tensor([0.0, 1.0, 0.0], device=device)), dim=0
                )
                up = torch.linalg.cross(right, forward)
                directions = forward + px[..., None] * right + py[..., None] * up
                origins = eye.expand(height * width, 3)
                shaded = shade(bvh, origins, directions.reshape(-1, 3), colors, face_colors=True)
                rgba = shaded.rgba.view(height, width, 4)
                image = rgba[..., :3] * rgba[..., 3:] + sky * (1.0 - rgba[..., 3:])
                writer.append_data((image.clamp(0, 1) * 255).to(torch.uint8).cpu().numpy())
        finally:
            writer.close()
    return Path(path)
