"""Where the project reads third-party data and keeps what it computes once.

* :data:`SHARED_DATA`: the shared data folder ``../shared/data`` beside the checkout (datasets such as
  ``nerf_synthetic_lego``); it is only read, never written.
* :func:`cache_root`: the cache of rendered scene views and fitted NeRF checkpoints, ``$PIE_CACHE_DIR`` or
  ``~/.cache/pie-physavatar`` unless a folder is given.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SHARED_DATA", "cache_root"]

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
"""The shared data folder beside the checkout (read only)."""


def cache_root(cache_dir: str | Path | None = None) -> Path:
    """The cache folder: ``cache_dir`` when given, else ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    return Path(os.environ.get("PIE_CACHE_DIR", Path.home() / ".cache" / "pie-physavatar")).expanduser()
