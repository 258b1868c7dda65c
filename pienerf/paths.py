"""Where the project reads third-party data and keeps what it computes once.

* :data:`SHARED_DATA`: the shared data folder, ``$PIE_SHARED_DATA`` or else ``../shared/data`` beside the checkout
  (datasets such as ``nerf_synthetic_lego``); it is only read, never written. Pointing ``PIE_SHARED_DATA`` at a
  missing folder runs the project as on a machine without it.
* :func:`cache_root`: the cache of rendered scene views and fitted NeRF checkpoints, ``$PIE_CACHE_DIR`` or
  ``~/.cache/pie-physavatar`` unless a folder is given.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SHARED_DATA", "cache_root"]

SHARED_DATA = Path(
    os.environ.get("PIE_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data"
).expanduser()
"""The shared data folder (read only): ``$PIE_SHARED_DATA``, else ``../shared/data`` beside the checkout."""


def cache_root(cache_dir: str | Path | None = None) -> Path:
    """The cache folder: ``cache_dir`` when given, else ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    return Path(os.environ.get("PIE_CACHE_DIR", Path.home() / ".cache" / "pie-physavatar")).expanduser()
