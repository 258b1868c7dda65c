"""Validation of a capture folder before any heavy work: every problem at once, each with its fix.

:func:`check_capture` reads the folder through the same parser as
:func:`~physavatar.capture.load_capture_folder` (:mod:`physavatar.capture.layout`), but collects every problem
instead of stopping at the first, opens the images one at a time (for their size and whether a mask is empty)
instead of holding them all, and then looks at the scene as a whole: the units, whether the garment is worn by
the body at time index 0, and which cameras see it. A garment that starts partly inside the body is not a problem
(the pipeline pushes it out before simulating); the check reports how many vertices and how deep.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from physavatar.body import surface_closest_points
from physavatar.capture.layout import (
    TRANSFORMS,
    UP_AXES,
    CaptureIndex,
    Findings,
    Problem,
    body_paths,
    boundary_path,
    garment_path,
    read_body,
    read_boundary,
    read_garment,
    read_index,
    read_view,
)
from physavatar.garment import MAX_GAP, Garment

__all__ = [
    "MAX_EXTENT",
    "CaptureCheck",
    "Problem",
    "check_capture",
]

MAX_EXTENT = 10.0
"""Largest size (m) of the body or the garment before its units are taken for millimetres."""
_EXACT_REACH = 0.5  # m: garment vertices surely farther than this from the body get a bound, not the exact distance
_CHUNK = 256  # garment vertices per closest-point batch (bounds the candidate triangles held at once)
_SCENE_ROWS = ("garment to body", "inside the body", "cameras seeing it")


@dataclass(frozen=True, eq=False)
class CaptureCheck:
    """What :func:`check_capture` found in a capture folder.

    Attributes:
        path: the capture folder.
        problems: what makes the capture unusable, each with its fix.
        warnings: what is usable but suspicious, in the same form.
        summary: ``(name, value)`` rows describing the capture as far as it could be read (``?`` where unknown).
    """

    path: Path
    problems: list[Problem]
    warnings: list[Problem]
    summary: list[tuple[str, str]]

    @property
    def ok(self) -> bool:
        """Whether the capture has no problem (warnings allowed)."""
        return not self.problems

    def format(self) -> str:
        """The report for a terminal: the summary table when ok, otherwise one block per problem (what is wrong and
        how to fix it); the warnings after either."""
        lines = []
        if self.ok:
            warned = f" ({len(self.warnings)} warning{'s' * (len(self.warnings) != 1)})" if self.warnings else ""
            lines.append(f"capture {self.path}: ok{warned}")
            width = max(len(name) for name, _ in self.summary)
            lines += [f"  {name:<{width}}  {value}" for name, value in self.summary]
        else:
            count = len(self.problems)
            lines.append(f"capture {self.path}: {count} problem{'s' * (count != 1)}")
            for number, problem in enumerate(self.problems, start=1):
                lines += ["", f"problem {number}: {problem.where}: {problem.what}", f"  fix: {problem.fix}"]
        for warning in self.warnings:
            lines += ["", f"warning: {warning.where}: {warning.what}", f"  fix: {warning.fix}"]
        return "\n".join(lines)


def check_capture(path: str | Path) -> CaptureCheck:
    """Check a capture folder against the format (``docs/capture.md``) and for a sound scene.

    Problems: a missing or malformed ``transforms.json`` or key; missing, unreadable or wrongly sized images and
    masks; cameras not numbered ``0..C−1``, a camera lacking a time index, moving cameras or intrinsics; fps missing
    or not positive; an up axis other than y or z; units other than metres; missing or unreadable body meshes, not
    one per time index, or a body whose topology changes; a garment mesh with zero-area or non-manifold triangles;
    boundary indices outside the garment; a body or garment larger than :data:`MAX_EXTENT` (millimetres); a garment
    whose nearest vertex lies farther than :data:`~physavatar.garment.MAX_GAP` from the body at time index 0; no
    camera seeing the garment. Warnings: a camera that does not see the garment, a camera whose garment masks are
    all empty, garment vertices starting inside the body, an up axis along which the body is short.

    Args:
        path: the capture folder (or its ``transforms.json``).

    Returns:
        The :class:`CaptureCheck`; it never raises for a bad capture.
    """
    path = Path(path)
    folder = path.parent if path.suffix == ".json" else path
    findings = Findings(folder, strict=False)
    rows: dict[str, str] = {}
    index = read_index(path, findings)
    meta = index.meta if index is not None else {}
    if index is not None:
        _check_views(index, findings)
        _describe_index(index, rows)
    body = garment = body_where = garment_where = None
    if folder.is_dir():
        paths = body_paths(folder, meta, None if index is None else len(index.times) or None, findings)
        body = None if paths is None else read_body(folder, paths, findings)
        body_where = "body/" if paths is None else _relative(folder, paths[0])
        garment_file = garment_path(folder, meta, findings)
        if garment_file is not None:
            garment = read_garment(folder, garment_file, findings)
            garment_where = _relative(folder, garment_file)
        boundary_file = boundary_path(folder, meta, findings)
        if boundary_file is None:
            rows["boundary"] = "automatic (no boundary.txt: the pipeline chooses the vertices and writes them out)"
        else:
            boundary = read_boundary(folder, boundary_file, garment, findings)
            rows["boundary"] = f"given: {'?' if boundary is None else len(boundary)} vertices ({boundary_file.name})"
    if body is not None:
        frames, faces = body
        rows["body"] = f"{len(frames)} meshes, {frames.shape[1]} vertices, {len(faces)} faces"
    if garment is not None:
        rows["garment"] = f"{len(garment.vertices)} vertices, {len(garment.faces)} faces ({garment_where})"
    metres = _check_units(body, garment, body_where, garment_where, findings)
    if metres and body is not None and garment is not None:
        up = "y" if index is None else index.up
        _check_scene(body[0][0].numpy(), body[1].numpy(), garment, up, garment_where, findings, rows)
    if metres and garment is not None and index is not None and index.rig is not None:
        _check_cameras(index, garment, findings, rows)
    order = ("frames", "cameras", "image size", "fps", "up", "body", "garment", "boundary", *_SCENE_ROWS)
    summary = [(name, rows.get(name, "?")) for name in order]
    return CaptureCheck(folder, findings.problems, findings.warnings, summary)


def _describe_index(index: CaptureIndex, rows: dict[str, str]) -> None:
    if index.views is not None:
        rows["frames"] = f"{index.frame_count} time indices"
        rows["cameras"] = str(index.camera_count)
    if index.size is not None:
        rows["image size"] = f"{index.size[0]} x {index.size[1]} px"
    if index.fps is not None:
        rows["fps"] = f"{index.fps:g}"
    rows["up"] = index.up + (" (turned to y-up on load)" if index.up == "z" else "")


def _check_views(index: CaptureIndex, findings: Findings) -> None:
    """Open every image and mask one at a time: missing, unreadable, wrongly sized; warn for a camera whose garment
    masks are empty in every view."""
    size = index.size
    masked: dict[int, bool] = {}
    keys = ("file_path", "mask_path", "body_mask_path")
    for k, frame in enumerate(index.frames):
        for key in keys:
            if not isinstance(frame.get(key), str):
                continue
            pixels = read_view(index.folder, frame, key, size, "L", findings, k)
            if pixels is None:
                continue
            size = size or (pixels.shape[1], pixels.shape[0])
            camera = frame.get("camera")
            if key == "mask_path" and isinstance(camera, int):
                masked[camera] = masked.get(camera, False) or bool((pixels >= 128).any())
    for camera, any_garment in sorted(masked.items()):
        if not any_garment:
            findings.warning(
                f"camera {camera}",
                "its garment masks are empty in every view (no pixel >= 128)",
                "check the masks of this camera: white (>= 128) marks the garment",
            )


def _check_units(
    body: tuple | None, garment: Garment | None, body_where: str, garment_where: str, findings: Findings
) -> bool:
    """Whether the meshes read look like metres (none larger than :data:`MAX_EXTENT`); a problem for each that
    does not."""
    metres = True
    meshes = (
        (body_where, "body", None if body is None else body[0][0]),
        (garment_where, "garment", None if garment is None else garment.vertices),
    )
    for where, name, vertices in meshes:
        if vertices is None:
            continue
        extent = float((vertices.amax(0) - vertices.amin(0)).max())
        if extent > MAX_EXTENT:
            metres = False
            findings.problem(
                where,
                f"the {name} spans {extent:.4g} m: its units look like millimetres",
                "scale by 0.001 (meshes and camera positions alike): a capture is read in metres",
            )
    return metres


def _check_scene(
    body: np.ndarray,
    body_faces: np.ndarray,
    garment: Garment,
    up: str,
    garment_where: str,
    findings: Findings,
    rows: dict[str, str],
) -> None:
    """The up axis and the garment on the body at time index 0 (``body [B, 3]``, capture axes, m)."""
    vertices = garment.vertices.numpy()
    body_extent = np.ptp(body, 0)
    axis = "xyz".index(up)
    if body_extent[axis] < 0.5 * body_extent.max():
        tallest = "xyz"[int(np.argmax(body_extent))]
        fix = (
            f'set "up": "{tallest}" if {tallest} points up'
            if tallest in UP_AXES
            else "turn the world so that y or z points up (meshes and cameras alike)"
        )
        findings.warning(
            TRANSFORMS,
            f"the body is {body_extent[axis]:.2f} m along the declared up axis {up} but {body_extent.max():.2f} m "
            f"along {tallest}",
            f"check the up axis: a standing body is tallest along it ({fix})",
        )
    distance, inside = _surface_distance(body, body_faces, vertices)
    closest = int(np.argmin(distance))
    nearest = float(distance[closest])
    side = "inside" if inside[closest] else "outside"
    rows["garment to body"] = f"nearest vertex {nearest * 1e3:.1f} mm {side} the body surface at time index 0"
    if nearest > MAX_GAP:
        findings.problem(
            garment_where,
            f"the garment is not on the body: its nearest vertex is {nearest * 1e3:.0f} mm from the body at time "
            f"index 0 (at most {MAX_GAP * 1e3:.0f} mm)",
            "place the garment where it is worn at time index 0, in the body's axes and units",
        )
    count = int(inside.sum())
    if count:
        depth = float(distance[inside].max())
        rows["inside the body"] = f"{count} of {len(vertices)} vertices, up to {depth * 1e3:.1f} mm deep"
        findings.warning(
            garment_where,
            f"{count} of {len(vertices)} garment vertices start inside the body at time index 0, up to "
            f"{depth * 1e3:.1f} mm deep",
            "nothing to do if few and shallow: the pipeline pushes them out before simulating",
        )
    else:
        rows["inside the body"] = f"0 of {len(vertices)} vertices"


def _check_cameras(index: CaptureIndex, garment: Garment, findings: Findings, rows: dict[str, str]) -> None:
    """Which cameras see the garment at time index 0: a vertex in front of the camera that projects into its
    image."""
    rig = index.rig
    pixels, depth = rig.project(garment.vertices)
    seen = (
        (depth > 0)
        & (pixels[..., 0] >= 0)
        & (pixels[..., 0] <= rig.width)
        & (pixels[..., 1] >= 0)
        & (pixels[..., 1] <= rig.height)
    )
    blind = [c for c in range(len(rig)) if not bool(seen[c].any())]
    seeing = len(rig) - len(blind)
    rows["cameras seeing it"] = f"{seeing} of {len(rig)}" + (f" (not camera {_list(blind)})" if blind else "")
    if seeing == 0:
        findings.problem(
            TRANSFORMS,
            "no camera sees the garment at time index 0: none of its vertices projects into any image",
            "check the cameras: transform_matrix is camera-to-world in the OpenGL convention (the camera looks "
            "along its -z axis; OpenCV poses need their y and z columns negated), in the meshes' axes and units",
        )
        return
    for c in blind:
        findings.warning(
            f"camera {c}",
            "does not see the garment at time index 0: none of its vertices projects into its image",
            f"check camera {c}'s transform_matrix (OpenGL convention, camera-to-world), or leave the camera out",
        )


def _surface_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance ``[P]`` (m) from each point to a closed triangle surface and whether it lies inside (``[P]`` bool).

    Exact closest points (:func:`~physavatar.body.surface_closest_points`), in batches; inside where the point lies
    behind the surface normal there, interpolated from the vertex normals (exact in sign near a smooth closed
    surface). Points certainly farther than ``_EXACT_REACH`` from the surface get their nearest vertex's distance
    (an upper bound) and count as outside: their candidate triangles would be most of the mesh.
    """
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    normals = np.asarray(mesh.vertex_normals)
    if mesh.is_watertight and mesh.volume < 0.0:  # inward-wound: its normals point in
        normals = -normals
    tri = vertices[faces]
    reach = float(np.linalg.norm(tri - tri.mean(1, keepdims=True), axis=2).max())
    upper, _ = cKDTree(vertices).query(points)
    distance, inside = upper.copy(), np.zeros(len(points), dtype=bool)
    near = np.flatnonzero(upper - 2.0 * reach <= _EXACT_REACH)  # a triangle's points lie within 2·reach of a corner
    body_vertices, body_faces = torch.from_numpy(vertices), torch.from_numpy(faces)
    for start in range(0, len(near), _CHUNK):
        rows = near[start : start + _CHUNK]
        q = torch.from_numpy(points[rows])
        closest, gap, face, bary = surface_closest_points(body_vertices, body_faces, q)
        normal = (bary[:, :, None].numpy() * normals[faces[face.numpy()]]).sum(1)
        distance[rows] = gap.numpy()
        inside[rows] = ((q - closest).numpy() * normal).sum(1) < 0.0
    return distance, inside


def _relative(folder: Path, path: Path) -> str:
    """``path`` as the problems name it: relative to the capture folder where it lies inside."""
    return path.relative_to(folder).as_posix() if path.is_relative_to(folder) else str(path)


def _list(values: list[int]) -> str:
    return ", ".join(str(v) for v in values)
