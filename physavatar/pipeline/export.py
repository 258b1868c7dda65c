"""The synthetic experiment's capture written as a user's capture folder, with a reconstruction's defects.

:func:`export_capture_folder` turns ``out/capture`` (the views the capture stage filmed, the body it moved and the
garment's first frame) into the folder layout of ``docs/capture.md``, so the stages of
:mod:`~physavatar.pipeline.user_capture` can be measured on it against a truth they never read: the garment
template is pushed into the body over a patch of its vertices, as a reconstruction that touches the body is, and
the world may be written z-up.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import numpy as np
import torch

from physavatar.body import surface_closest_points
from physavatar.capture import to_capture_axes
from physavatar.result_files import Staging, write_json, write_obj, write_text

__all__ = ["export_capture_folder"]


def export_capture_folder(
    out: Path,
    folder: Path,
    push_depth: float = 3e-3,
    push_fraction: float = 0.05,
    up: str = "z",
    staging: Staging = contextlib.nullcontext,
) -> dict:
    """Write the synthetic experiment's capture (``out/capture``) as a user's capture folder.

    The template ``garment.obj`` is the garment's first frame with the ``push_fraction`` of its non-boundary
    vertices nearest the body moved to ``push_depth`` inside it (along the normal of their closest body triangle);
    ``boundary.txt`` holds the experiment's boundary vertices; ``body/frame_XXXX.obj`` the body per frame; the
    images and masks are copied.

    Args:
        out: the experiment folder whose capture stage has run.
        folder: the capture folder to write (created).
        push_depth: how far inside the body the pushed vertices start, m.
        push_fraction: the fraction of the garment's vertices pushed in.
        up: ``"z"`` writes a z-up world, ``"y"`` keeps the project's axes.
        staging: the step every file is written through.

    Returns:
        ``{"pushed": [indices], "push_depth_m": ..., "up": ...}``, also written as ``export.json`` beside the
        capture folder's other files (the pipeline does not read it).

    Raises:
        FileNotFoundError: the capture stage has not run in ``out``.
        ValueError: ``up``, ``push_depth`` or ``push_fraction`` out of range.
    """
    if up not in ("y", "z"):
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    if not 0.0 <= push_depth <= 0.05 or not 0.0 <= push_fraction <= 0.5:
        raise ValueError(
            f"push_depth must lie in [0, 0.05] m and push_fraction in [0, 0.5], got {push_depth}, {push_fraction}"
        )
    source = Path(out) / "capture"
    inputs_path = source / "inputs.npz"
    if not inputs_path.is_file():
        raise FileNotFoundError(f"{inputs_path} is missing; run the capture stage first: python -m apps.avatar capture")
    with np.load(inputs_path) as data:
        given = {k: torch.from_numpy(data[k]) for k in data.files}
    first, faces = given["first_vertices"].to(torch.float64), given["faces"].long()
    body_frames, body_faces = given["body_frames"].to(torch.float64), given["body_faces"].long()
    boundary = given["boundary_index"].long()

    closest, distance, face, _ = surface_closest_points(body_frames[0], body_faces, first)
    corners = body_frames[0][body_faces[face]]
    normal = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=1)
    normal = normal / torch.linalg.vector_norm(normal, dim=1, keepdim=True)
    free = torch.ones(first.shape[0], dtype=torch.bool)
    free[boundary] = False
    count = int(round(push_fraction * first.shape[0]))
    order = torch.argsort(torch.where(free, distance, torch.full_like(distance, float("inf"))))
    pushed = order[:count].sort().values
    template = first.clone()
    template[pushed] = closest[pushed] - push_depth * normal[pushed]

    folder = Path(folder)
    for sub in ("images", "masks", "body"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    meta = json.loads((source / "transforms.json").read_text())
    world = torch.eye(4, dtype=torch.float64)
    world[:3, :3] = to_capture_axes(torch.eye(3, dtype=torch.float64), up).T  # acting on column vectors
    for frame in meta["frames"]:
        for key in ("file_path", "mask_path"):
            name = Path(frame[key]).name
            with staging(folder / Path(frame[key]).parent.name / name) as target:
                shutil.copyfile(source / frame[key], target)
        frame["transform_matrix"] = (world @ torch.tensor(frame["transform_matrix"], dtype=torch.float64)).tolist()
    for key in ("lighting", "background"):
        meta.pop(key, None)  # a user's capture records neither: the appearance stage recovers the light
    for t, vertices in enumerate(body_frames):
        write_obj(folder / "body" / f"frame_{t:04d}.obj", to_capture_axes(vertices, up), body_faces, staging)
    pushed_in = "the garment at frame 0, pushed into the body"
    write_obj(folder / "garment.obj", to_capture_axes(template, up), faces, staging, pushed_in)
    write_text(folder / "boundary.txt", "\n".join(str(int(i)) for i in boundary) + "\n", staging)
    record = {"pushed": pushed.tolist(), "push_depth_m": push_depth, "up": up}
    write_json(folder / "export.json", record, staging)
    write_json(folder / "transforms.json", {**meta, "up": up, "units": "m"}, staging, indent=1)
    return record
