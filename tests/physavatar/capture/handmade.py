"""A small capture folder written by hand, file by file, as a researcher would lay one out (``docs/capture.md``).

The scene, in y-up world axes (metres): a standing capsule body (1.5 m, a few hundred triangles) that slides along x
by 1 cm per time index, an open tube garment 5 cm around its hips, and two 32 × 24 cameras 2.5 m away looking at
it. A z-up folder holds the same scene turned by ``(x, y, z) → (x, −z, y)``, the inverse of the loader's turn.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from physavatar.capture import CameraRig

WIDTH, HEIGHT = 32, 24  # px
FPS = 30.0
FRAMES, CAMERAS = 3, 2
RING = 12  # garment vertices per ring
GARMENT_RADIUS = 0.2  # m, 5 cm outside the body


def body_mesh(t: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``[B, 3]`` vertices (y-up, m) of the body at time index ``t`` and its ``[G, 3]`` faces."""
    capsule = trimesh.creation.capsule(height=1.2, radius=0.15, count=[12, 12])
    turned = np.asarray(capsule.vertices) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return turned + np.array([0.01 * t, 0.0, 0.0]), np.asarray(capsule.faces)


def garment_mesh() -> tuple[np.ndarray, np.ndarray]:
    """An open tube: 3 rings of :data:`RING` vertices from y = −0.1 to 0.2 m, outward-wound (36 vertices, 48
    faces)."""
    angle = 2.0 * math.pi * np.arange(RING) / RING
    rings = [
        np.stack([GARMENT_RADIUS * np.sin(angle), np.full(RING, y), GARMENT_RADIUS * np.cos(angle)], 1)
        for y in (0.2, 0.05, -0.1)
    ]
    faces = []
    for r in range(2):
        for s in range(RING):
            a, b = r * RING + s, r * RING + (s + 1) % RING
            faces += [(a, a + RING, b), (b, a + RING, b + RING)]
    return np.concatenate(rings), np.asarray(faces)


def camera_rig() -> CameraRig:
    """Two cameras (y-up) on the +z and +x axes, 2.5 m from the origin, looking at it (40° vertical field)."""
    return CameraRig.look_at([[0.0, 0.1, 2.5], [2.5, 0.1, 0.0]], [0.0, 0.0, 0.0], WIDTH, HEIGHT, 40.0)


def to_z_up(points: np.ndarray) -> np.ndarray:
    """``[..., 3]`` y-up points in z-up axes: ``(x, y, z) → (x, −z, y)``."""
    return np.stack([points[..., 0], -points[..., 2], points[..., 1]], -1)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, extra: str = "") -> None:
    """An OBJ with every coordinate written exactly (shortest round-trip repr)."""
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n" + extra)


def image_name(camera: int, time: int) -> str:
    return f"c{camera}_t{time}.png"


def write_capture_folder(folder: Path, up: str = "y") -> dict:
    """Write the scene as a capture folder and return its ``transforms.json`` object.

    Images are seeded noise; each garment mask is a white rectangle in the middle of the image.
    """
    turn = to_z_up if up == "z" else (lambda points: points)
    folder.mkdir(parents=True)
    for t in range(FRAMES):
        vertices, faces = body_mesh(t)
        write_obj(folder / "body" / f"{t:04d}.obj", turn(vertices), faces)
    vertices, faces = garment_mesh()
    write_obj(folder / "garment.obj", turn(vertices), faces)
    generator = np.random.default_rng(0)
    (folder / "images").mkdir()
    (folder / "masks").mkdir()
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    mask[8:16, 10:22] = 255
    c2w = camera_rig().c2w.numpy()
    if up == "z":
        c2w = np.concatenate([to_z_up(c2w[:, :3, :].transpose(0, 2, 1)).transpose(0, 2, 1), c2w[:, 3:]], 1)
    frames = []
    for t in range(FRAMES):
        for c in range(CAMERAS):
            name = image_name(c, t)
            Image.fromarray(generator.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)).save(
                folder / "images" / name
            )
            Image.fromarray(mask).save(folder / "masks" / name)
            frames.append(
                {
                    "file_path": f"images/{name}",
                    "mask_path": f"masks/{name}",
                    "camera": c,
                    "time_index": t,
                    "transform_matrix": c2w[c].tolist(),
                }
            )
    rig = camera_rig()
    meta = {
        "fps": FPS,
        "up": up,
        "units": "m",
        "w": WIDTH,
        "h": HEIGHT,
        "fl_x": float(rig.fx[0]),
        "fl_y": float(rig.fy[0]),
        "cx": float(rig.cx[0]),
        "cy": float(rig.cy[0]),
        "frames": frames,
    }
    (folder / "transforms.json").write_text(json.dumps(meta, indent=1))
    return meta


def edit_json(folder: Path, change) -> None:
    """Apply ``change(meta)`` to the folder's ``transforms.json`` object in place."""
    path = folder / "transforms.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def frame_of(meta: dict, camera: int, time: int) -> dict:
    return next(f for f in meta["frames"] if (f["camera"], f["time_index"]) == (camera, time))
