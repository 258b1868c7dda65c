"""Result files of the PhysAvatar stages, each written through a staging step the program passes in.

``staging(path)`` is a context manager that yields the file to write for ``path`` and puts it at ``path`` once its
block ends cleanly. The default, :func:`contextlib.nullcontext`, writes ``path`` itself; a program passes one that
writes a temporary file beside ``path`` and moves it into place (``pienerf.output_files.atomic_path``), so that an
interrupted write (Ctrl-C, a full disk) leaves no half-written file and keeps an earlier file at ``path``. The step
is a parameter because this package does not import ``pienerf``: the temporary-file logic lives there, once.

The writers below keep only the format logic, and name the format explicitly, so the file the staging step yields
may be called anything.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["Staging", "save_figure", "write_arrays", "write_json", "write_obj", "write_png", "write_text"]

Staging = Callable[[Path], contextlib.AbstractContextManager[Path]]
"""``staging(path)``: a context manager yielding the file to write for ``path``, in place at ``path`` after a clean
exit of its block (see the module docstring)."""


def write_text(path: str | Path, text: str, staging: Staging = contextlib.nullcontext) -> Path:
    """``text`` as a UTF-8 file at ``path``, written through ``staging``."""
    path = Path(path)
    with staging(path) as target, open(target, "w", encoding="utf-8") as file:
        file.write(text)
    return path


def write_json(path: str | Path, value, staging: Staging = contextlib.nullcontext, indent: int = 2) -> Path:
    """``value`` as indented JSON at ``path``, written through ``staging``."""
    path = Path(path)
    with staging(path) as target, open(target, "w", encoding="utf-8") as file:
        json.dump(value, file, indent=indent)
    return path


def write_obj(
    path: str | Path, vertices, faces, staging: Staging = contextlib.nullcontext, comment: str | None = None
) -> Path:
    """A triangle mesh ``vertices [V, 3]``, ``faces [F, 3]`` (0-based) as a Wavefront OBJ at ``path`` (1-based
    ``f`` lines, 9 significant digits: exact to 1e-9 of a metre-sized mesh), written through ``staging``."""
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    lines = [f"# {comment}"] if comment else []
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    return write_text(path, "\n".join(lines) + "\n", staging)


def write_arrays(path: str | Path, staging: Staging = contextlib.nullcontext, **arrays) -> Path:
    """``arrays`` (name → array or number) as a compressed NPZ at ``path`` exactly (NumPy adds no ``.npz``),
    written through ``staging``."""
    path = Path(path)
    with staging(path) as target, open(target, "wb") as file:
        np.savez_compressed(file, **arrays)
    return path


def write_png(path: str | Path, image: np.ndarray, staging: Staging = contextlib.nullcontext) -> Path:
    """An 8-bit image ``[H, W, 3]`` (RGB) or ``[H, W]`` (grey) as a PNG at ``path``, written through ``staging``."""
    from PIL import Image  # deferred: Pillow is needed only where images are written

    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"a PNG needs uint8 [H, W, 3] or [H, W] pixels, got {image.dtype} {list(image.shape)}")
    path = Path(path)
    with staging(path) as target:
        Image.fromarray(image, "RGB" if image.ndim == 3 else "L").save(target, format="PNG")
    return path


def save_figure(figure, path: str | Path, staging: Staging = contextlib.nullcontext, dpi: int = 120) -> Path:
    """A Matplotlib figure at ``path`` in the format its suffix names (``.png``, ``.pdf``, ``.svg``), at ``dpi``
    dots per inch, written through ``staging``."""
    path = Path(path)
    with staging(path) as target:
        figure.savefig(target, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    return path
