"""A user capture folder built by hand from files, as a researcher builds one from a studio recording.

The project's own capture writer (:func:`physavatar.capture.write_capture`) makes a folder the pipeline trivially
agrees with. A user's folder is made of other files: an OBJ body sequence exported from a body fit, an OBJ garment
from a reconstruction, PNG images and masks named their own way, and a ``transforms.json`` typed by hand, in a
z-up world, with one camera calibrated apart. :func:`build_handmade_capture` writes such a folder, with the defects
real inputs carry:

* the body intersects itself, as many SMPL-X fits do: the left upper arm is turned into the chest in every frame
  (about 2–3 cm deep; the elbow dips into the waist), its forearm bent out so that the hand clears the skirt;
* the garment template is not the first true frame: a contiguous patch of about 5 % of its vertices lies 3–5 mm
  inside the body, as a reconstruction leaves it;
* the cameras stand at scattered heights, distances and azimuths, each aimed at its own point, and the last one
  has its own focal lengths and principal point (per-frame ``fl_x``/``fl_y``/``cx``/``cy``).

The scene is the project's: the mannequin walking (:func:`physavatar.body.named_motion`), the procedural skirt
simulated with :data:`physavatar.fit.estimation.SYNTHETIC_FABRIC`, filmed by
:func:`physavatar.capture.render_capture` in the project's y-up axes. Every file is written in the capture's z-up
axes: a y-up point ``(x, y, z)`` is ``(x, −z, y)`` there, and the loader turns it back with :data:`Y_UP_FROM_Z_UP`.

Tests that need the folder build it once per session with a fixture such as::

    @pytest.fixture(scope="session")
    def handmade(tmp_path_factory):
        folder = tmp_path_factory.mktemp("handmade")
        return folder, build_handmade_capture(folder)

and never write into it (copy it with ``shutil.copytree`` to break it on purpose). At the default size the build
takes about 2.5 s on a 2-core CPU, 1.5 s of it the mannequin's surface extraction, which a process does once: a
second capture takes under 1 s.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from scipy.spatial import cKDTree

from physavatar.body import Body, Motion, axis_angle_to_matrix, named_motion
from physavatar.capture import CameraRig, Lighting, garment_albedo, render_capture
from physavatar.drive import BodyDriver
from physavatar.fit.estimation import SYNTHETIC_FABRIC, EstimationProblem, FabricParameters, rollout
from physavatar.garment import procedural_skirt, select_boundary

__all__ = [
    "ARM_JOINTS",
    "FPS",
    "Y_UP_FROM_Z_UP",
    "build_handmade_capture",
    "read_obj",
]

FPS = 30.0
"""Frames per second of the capture."""

Y_UP_FROM_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking the capture's z-up points to the project's y-up axes, ``(x, y, z) → (x, z, −y)``:
``p_y = Y_UP_FROM_Z_UP @ p_z``; its transpose goes back."""

ARM_JOINTS = ("left_shoulder", "left_elbow", "left_wrist")
"""Joints of the arm turned into the torso; a body vertex belongs to that arm when their weights sum over ½."""

_SHOULDER_DROP = 0.95  # rad about −z: the left upper arm from 45° below horizontal to 9° past vertical, into the chest
_ELBOW_LIFT = 1.35  # rad about +z: the forearm back out to 22° below horizontal, its hand clear of the skirt
_SKIRT_RINGS, _SKIRT_SEGMENTS = 6, 16
_PUSH_FRACTION = 0.05  # of the garment's vertices pushed into the body in the template
_PUSH_DEPTH = (3.3e-3, 4.7e-3)  # m, depth range of the pushed vertices (inside the 3–5 mm they are promised)
_HEIGHTS, _DISTANCES = (0.3, 1.6), (1.8, 3.0)  # m, camera heights above the floor and distances from the body axis
_AIM = np.array([0.0, 0.0, 0.86])  # m, z-up: the middle of the skirt, where the cameras aim (each jittered)
_FOV_DEG = 24.0  # vertical field of view of the shared intrinsics
_ODD_FOCAL, _ODD_ASPECT, _ODD_SHIFT = 1.15, 1.004, (1.7, -1.3)  # the last camera's intrinsics, relative / pixels
_SKIN = (0.78, 0.74, 0.68)
_INSIDE = 1.0  # winding number of a surface vertex: ½ on its own part, 1½ inside another part


def build_handmade_capture(
    folder: Path,
    frames: int = 4,
    cameras: int = 3,
    size: tuple[int, int] = (48, 40),
    seed: int = 0,
    *,
    boundary: bool = False,
) -> dict:
    """Write a z-up user capture folder from hand-made files (the module docstring lists its defects).

    Files: ``body/frame_0000.obj`` … (one per frame, one topology), ``garment.obj`` (the template),
    ``images/cam{c}_t{t}.png`` and ``masks/cam{c}_t{t}.png`` (white = garment), ``transforms.json`` (frames listed
    camera by camera) and, with ``boundary``, ``boundary.txt``.

    Args:
        folder: created if missing; files already there are overwritten.
        frames: time indices ``T`` (≥ 2), one simulation step of ``1 / FPS`` s between them.
        cameras: cameras ``C`` (≥ 2: the last one has its own intrinsics).
        size: ``(width, height)`` of every image, px (≥ 16 each).
        seed: seed of the camera placement and of the pushed patch.
        boundary: also write ``boundary.txt``: the skirt's waistband (what ``select_boundary`` picks), 0-based.

    Returns:
        A dict, arrays in numpy, lengths in metres, in the capture's z-up axes unless named ``*_y_up``:
        ``folder`` (Path), ``fps`` (float), ``frames``, ``cameras``, ``size``;
        ``garment_frames`` ``[T, V, 3]`` the true garment per frame (the simulation the images show);
        ``garment_faces`` ``[F, 3]``; ``template`` ``[V, 3]`` (what ``garment.obj`` holds);
        ``pushed`` ``[K]`` template vertices pushed into the body, ``push_depth`` ``[K]`` how deep (the frame-0
        body's signed distance, negated);
        ``body_frames`` ``[T, B, 3]``, ``body_faces`` ``[Fb, 3]``; ``arm_vertices`` ``[A]`` the body vertices of the
        turned arm; ``intersecting`` ``[N]`` body vertices inside another part of the frame-0 body (arm in
        chest, chest in arm);
        ``boundary`` ``[D]`` the waistband vertices (written to ``boundary.txt`` only with ``boundary``);
        ``camera_list``: per camera a dict of ``c2w`` ``[4, 4]`` (OpenGL camera-to-world), ``fl_x``, ``fl_y``,
        ``cx``, ``cy`` (px), ``w``, ``h``; ``odd_camera``: the index of the one with its own intrinsics.

    Raises:
        ValueError: fewer than 2 frames or 2 cameras, or images under 16 px.
    """
    if frames < 2 or cameras < 2:
        raise ValueError(f"need frames >= 2 and cameras >= 2 (one with its own intrinsics), got {frames}, {cameras}")
    width, height = (int(s) for s in size)
    if min(width, height) < 16:
        raise ValueError(f"images must be at least 16x16 px for the skirt to show, got {width}x{height}")
    folder = Path(folder)
    rng = np.random.default_rng(seed)

    body = _mannequin()
    motion = _arm_in_torso(named_motion("walk", body.skeleton, frames - 1, FPS), body)
    skirt = procedural_skirt(body, rings=_SKIRT_RINGS, segments=_SKIRT_SEGMENTS)
    waist = select_boundary(skirt, body, mode="waist")
    driver = BodyDriver.from_motion(body, motion, skirt.vertices, waist, frames - 1)
    problem = EstimationProblem(
        skirt.vertices,
        skirt.faces,
        skirt.vertices.expand(frames, -1, -1),
        driver.body_frames,
        body.faces,
        driver.boundary_index,
        driver.boundary_targets,
        FPS,
        SYNTHETIC_FABRIC,
    )
    truth = rollout(problem, FabricParameters.from_config(SYNTHETIC_FABRIC)).frames  # [T, V, 3], y-up
    body_frames = driver.body_frames

    arm = body.weights[:, [body.skeleton.index(j) for j in ARM_JOINTS]].sum(1).numpy() > 0.5
    intersecting = _intersecting(body, body_frames[0], arm)
    pushed, template, depth = _push_patch(skirt.vertices, skirt.faces, waist, body, body_frames[0], rng)

    c2w, intrinsics, odd = _cameras(cameras, width, height, rng)
    images, masks = _film(truth, skirt.faces, body_frames, body.faces, c2w, intrinsics, width, height, seed)

    for t in range(frames):
        _write_obj(folder / "body" / f"frame_{t:04d}.obj", _z_up(body_frames[t]), body.faces.numpy(), "body fit")
    _write_obj(folder / "garment.obj", _z_up(template), skirt.faces.numpy(), "garment reconstruction, frame 0")
    if boundary:
        lines = ["# garment vertices that follow the body (0-based)", " ".join(str(int(i)) for i in waist)]
        (folder / "boundary.txt").write_text("\n".join(lines) + "\n")
    records = []
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    for c in range(cameras):
        for t in range(frames):
            name = f"cam{c}_t{t}.png"
            Image.fromarray(images[t, c]).save(folder / "images" / name)
            Image.fromarray(masks[t, c]).save(folder / "masks" / name)
            record = {
                "file_path": f"images/{name}",
                "mask_path": f"masks/{name}",
                "camera": c,
                "time_index": t,
                "transform_matrix": c2w[c].tolist(),
            }
            if c == odd:
                record.update(intrinsics[c])
            records.append(record)
    meta = {"fps": FPS, "up": "z", "units": "m", "w": width, "h": height, **intrinsics[0]}
    head = json.dumps(meta, indent=2)[:-2]  # without its closing "\n}": the frames follow, one line each
    lines = ",\n".join("    " + json.dumps(record) for record in records)
    (folder / "transforms.json").write_text(f'{head},\n  "frames": [\n{lines}\n  ]\n}}\n')

    return {
        "folder": folder,
        "fps": FPS,
        "frames": frames,
        "cameras": cameras,
        "size": (width, height),
        "garment_frames": _z_up(truth),
        "garment_faces": skirt.faces.numpy(),
        "template": _z_up(template),
        "pushed": pushed,
        "push_depth": depth,
        "body_frames": _z_up(body_frames),
        "body_faces": body.faces.numpy(),
        "arm_vertices": np.flatnonzero(arm),
        "intersecting": intersecting,
        "boundary": waist.numpy(),
        "camera_list": [{"c2w": c2w[c], **intrinsics[c], "w": width, "h": height} for c in range(cameras)],
        "odd_camera": odd,
    }


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``v`` and ``f`` lines of an OBJ file: ``(vertices [V, 3], faces [F, 3] 0-based)``; triangles only."""
    vertices, faces = [], []
    for line in Path(path).read_text().splitlines():
        fields = line.split()
        if fields and fields[0] == "v":
            vertices.append([float(x) for x in fields[1:4]])
        elif fields and fields[0] == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in fields[1:4]])
    return np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)


# ---------------------------------------------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------------------------------------------


@functools.cache
def _mannequin() -> Body:
    """The mannequin at the coarsest spacing allowed (7356 vertices), built once per process (1.5 s)."""
    return Body.mannequin(spacing=0.03)


def _arm_in_torso(motion: Motion, body: Body) -> Motion:
    """``motion`` with the left upper arm turned into the chest and the forearm bent back out, in every frame.

    The turn comes first and the motion's own rotation after it (``R = R_motion · R_turn``), as if the arm's rest
    pose hung lower: the walk's arm swing stays a swing about the shoulder.
    """
    skeleton = body.skeleton
    turn = torch.zeros(skeleton.num_joints, 3, dtype=motion.rotations.dtype)
    turn[skeleton.index("left_shoulder"), 2] = -_SHOULDER_DROP
    turn[skeleton.index("left_elbow"), 2] = _ELBOW_LIFT
    rotations = motion.rotations @ axis_angle_to_matrix(turn)
    return Motion(rotations, motion.root_translation, motion.fps, motion.joint_names)


def _intersecting(body: Body, vertices: torch.Tensor, arm: np.ndarray) -> np.ndarray:
    """Body vertices inside another part of the posed body (winding number above 1), searched where the arm and
    the rest of the body come within 3 cm of each other."""
    v = vertices.numpy()
    arm_index, rest_index = np.flatnonzero(arm), np.flatnonzero(~arm)
    near_rest = cKDTree(v[rest_index]).query(v[arm_index], distance_upper_bound=0.03)[0] < 0.03
    near_arm = cKDTree(v[arm_index]).query(v[rest_index], distance_upper_bound=0.03)[0] < 0.03
    candidates = np.concatenate([arm_index[near_rest], rest_index[near_arm]])
    winding = body.winding_number(vertices[candidates].float(), vertices)
    return np.sort(candidates[winding.numpy() > _INSIDE])


def _push_patch(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    waist: torch.Tensor,
    body: Body,
    body_vertices: torch.Tensor,
    rng: np.random.Generator,
) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """A contiguous patch of about 5 % of the garment's vertices, away from its open edges, moved inside the body.

    The patch grows from a vertex close to the body (among the closest quarter) through the mesh's edges, nearest
    first; each vertex moves from ``x`` past its closest body point ``c`` along ``c − x`` (the body's normal there)
    to a depth drawn from 3.3–4.7 mm.

    Returns:
        ``(pushed [K], template [V, 3], depth [K])``: the indices, the garment with them moved (y-up) and their
        depth measured by the body's signed distance, m.
    """
    f = faces.numpy()
    v = vertices.numpy()
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    pairs, uses = np.unique(np.sort(edges, 1), axis=0, return_counts=True)
    edge_of = set(np.concatenate([pairs[uses == 1].ravel(), waist.numpy()]).tolist())
    interior = np.array([i for i in range(len(v)) if i not in edge_of])
    neighbours = [set() for _ in range(len(v))]
    for a, b in pairs:
        neighbours[a].add(b)
        neighbours[b].add(a)
    closest, distance, _, _ = body.closest_points(vertices[interior], body_vertices)
    order = np.argsort(distance.numpy())
    seed = int(interior[rng.choice(order[: max(1, len(order) // 4)])])
    size = max(3, round(_PUSH_FRACTION * len(v)))
    patch, frontier = [seed], set(neighbours[seed])
    allowed = set(interior.tolist())
    while len(patch) < size:
        options = sorted(i for i in frontier if i in allowed and i not in patch)
        nearest = min(options, key=lambda i: float(np.linalg.norm(v[i] - v[seed])))
        patch.append(nearest)
        frontier |= neighbours[nearest]
    pushed = np.sort(np.asarray(patch))
    x = vertices[pushed]
    closest, _, _, _ = body.closest_points(x, body_vertices)
    inward = torch.nn.functional.normalize(closest - x, dim=1)
    target = torch.as_tensor(rng.uniform(*_PUSH_DEPTH, size=len(pushed)), dtype=x.dtype)
    template = vertices.clone()
    template[pushed] = closest + inward * target[:, None]
    depth = -body.signed_distance(template[pushed], body_vertices).numpy()
    return pushed, template, depth


# ---------------------------------------------------------------------------------------------------------------
# Cameras and film
# ---------------------------------------------------------------------------------------------------------------


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``[4, 4]`` OpenGL camera-to-world matrix of a camera at ``eye`` looking at ``target``, z up in the image."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, eye
    return c2w


def _cameras(count: int, width: int, height: int, rng: np.random.Generator) -> tuple[np.ndarray, list[dict], int]:
    """Scattered z-up cameras: ``(c2w [C, 4, 4], intrinsics per camera, index of the odd one)``.

    Azimuths spread around the body with up to ±35 % of their spacing as jitter; heights and distances drawn
    uniformly; each camera aims within 5 cm of the skirt's middle.
    """
    step = 2.0 * math.pi / count
    azimuth = step * (np.arange(count) + rng.uniform(-0.35, 0.35, count))
    radius = rng.uniform(*_DISTANCES, count)
    eyes = np.stack([radius * np.sin(azimuth), -radius * np.cos(azimuth), rng.uniform(*_HEIGHTS, count)], 1)
    aims = _AIM + rng.uniform(-0.05, 0.05, (count, 3))
    c2w = np.stack([_look_at(e, a) for e, a in zip(eyes, aims, strict=True)])
    focal = 0.5 * height / math.tan(math.radians(_FOV_DEG) / 2.0)
    shared = {"fl_x": focal, "fl_y": focal, "cx": 0.5 * width, "cy": 0.5 * height}
    odd = count - 1
    own = {
        "fl_x": _ODD_FOCAL * focal,
        "fl_y": _ODD_FOCAL * _ODD_ASPECT * focal,
        "cx": 0.5 * width + _ODD_SHIFT[0],
        "cy": 0.5 * height + _ODD_SHIFT[1],
    }
    return c2w, [own if c == odd else dict(shared) for c in range(count)], odd


def _film(
    garment_frames: torch.Tensor,
    garment_faces: torch.Tensor,
    body_frames: torch.Tensor,
    body_faces: torch.Tensor,
    c2w: np.ndarray,
    intrinsics: list[dict],
    width: int,
    height: int,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Render every camera in the project's y-up axes, one rig per distinct intrinsics.

    Returns:
        ``(images [T, C, H, W, 3] uint8, masks [T, C, H, W] uint8 in {0, 255})``.
    """
    rotate = np.eye(4)
    rotate[:3, :3] = Y_UP_FROM_Z_UP
    c2w_y_up = torch.from_numpy(rotate @ c2w)
    albedo = garment_albedo(garment_frames[0], garment_faces, pattern="checks", bands=6)
    groups: dict[tuple, list[int]] = {}
    for c, k in enumerate(intrinsics):
        groups.setdefault(tuple(k.values()), []).append(c)
    frames, count = garment_frames.shape[0], len(intrinsics)
    images = np.empty((frames, count, height, width, 3), dtype=np.uint8)
    masks = np.empty((frames, count, height, width), dtype=np.uint8)
    for index in groups.values():
        k = intrinsics[index[0]]
        rig = CameraRig(c2w_y_up[index], width, height, k["fl_x"], k["fl_y"], k["cx"], k["cy"])
        film = render_capture(
            garment_frames, garment_faces, body_frames, body_faces, albedo, _SKIN, rig, Lighting(), FPS,
            ao_samples=4, seed=seed,
        )  # fmt: skip
        images[:, index] = torch.round(film.images * 255.0).to(torch.uint8).numpy()
        masks[:, index] = film.masks.numpy().astype(np.uint8) * 255
    return images, masks


# ---------------------------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------------------------


def _z_up(points: torch.Tensor) -> np.ndarray:
    """y-up points ``[..., 3]`` in the capture's z-up axes, ``(x, y, z) → (x, −z, y)``."""
    return points.detach().cpu().double().numpy() @ Y_UP_FROM_Z_UP


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, what: str) -> None:
    """A plain OBJ file: a comment, ``v x y z`` lines (m) and ``f a b c`` lines (1-based)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# {what}: {len(vertices)} vertices, {len(faces)} triangles, metres, z up"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
