"""Output files that never come out half-written, and output paths checked before any work is spent on them.

A program that runs for minutes and is then stopped (Ctrl-C, a full disk, a crash) must neither leave a truncated
file where a reader expects a whole one nor lose what it finished. :func:`atomic_path` hands out a temporary file in
the target's own folder and moves it over the target (``os.replace``, atomic on one file system) only once it is
complete; :func:`write_json` writes a JSON file that way, and :func:`staged_folder` a whole folder (a temporary
folder beside it, renamed into place once everything in it is written). :func:`check_output_folder` and
:func:`check_output_file` refuse, up front, a path that could not be written.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "OutputPathError",
    "atomic_path",
    "check_output_file",
    "check_output_folder",
    "staged_folder",
    "stale_staging_folders",
    "write_json",
]


class OutputPathError(ValueError):
    """An output path cannot be written; the message names the path, the flag and the fix."""


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """A temporary path beside ``path`` (same folder, same suffix, so writers pick the same format) to write to.

    On a clean exit of the ``with`` block it replaces ``path`` in one step; on any exception (``KeyboardInterrupt``
    included) it is removed and ``path`` is left as it was.
    """
    path = Path(path)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".partial{path.suffix}")
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        os.chmod(temporary, 0o644)  # mkstemp makes it owner-only; a result file is for everyone to read
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_json(path: Path | str, value, **dump_options) -> None:
    """Write ``value`` as indented JSON to ``path`` atomically (never half a file); ``dump_options`` go to
    :func:`json.dump` (``default=str`` for paths and the like)."""
    with atomic_path(path) as temporary, open(temporary, "w") as file:
        json.dump(value, file, indent=2, **dump_options)


@contextmanager
def staged_folder(path: Path | str) -> Iterator[Path]:
    """A temporary folder beside ``path`` (``.NAME.XXXX.partial``) to write a whole result folder into.

    On a clean exit of the ``with`` block the folder takes ``path``'s place: an earlier folder there is first moved
    aside and removed once the new one is in place, so a reader sees the old folder or the new one, never a mix. On
    any exception (``KeyboardInterrupt`` included) the temporary folder is removed and ``path`` is left as it was. A
    process killed inside the block leaves its temporary folder behind; :func:`stale_staging_folders` finds those.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".partial"))
    try:
        yield temporary
        os.chmod(temporary, 0o755)  # mkdtemp makes it owner-only; a result folder is for everyone to read
        if path.exists():
            aside = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
            os.replace(path, aside / path.name)
            os.replace(temporary, path)
            shutil.rmtree(aside, ignore_errors=True)
        else:
            os.replace(temporary, path)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise


def stale_staging_folders(path: Path | str) -> list[Path]:
    """The temporary folders :func:`staged_folder` left beside ``path`` when its process was killed (``.partial``)
    or stopped between the two renames (``.old``)."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    return sorted(
        p for suffix in (".partial", ".old") for p in path.parent.glob(f".{path.name}.*{suffix}") if p.is_dir()
    )


def _nearest_existing(path: Path) -> Path:
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    return existing


def check_output_folder(folder: Path | str, flag: str = "--out") -> None:
    """Refuse a folder that cannot be created or written into, before any work.

    Raises:
        OutputPathError: ``folder`` (or the nearest of its parents that exists) is a file or is not writable.
    """
    folder = Path(folder)
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        what = f"{flag} {folder}" if existing == folder else f"{flag}'s parent {existing}"
        raise OutputPathError(f"{what} is a file, not a folder; pass a folder path for the results (it is created)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write into {existing}; pass a {flag} folder you may write to")


def check_output_file(file: Path | str, flag: str) -> None:
    """Refuse a file path that cannot be written (a folder, or under a folder that cannot be), before any work.

    Raises:
        OutputPathError: as :func:`check_output_folder`, or ``file`` is a folder.
    """
    file = Path(file)
    if file.is_dir():
        raise OutputPathError(f"{flag} {file} is a folder; pass a file path such as {file / 'results.json'}")
    if file.exists() and not os.access(file, os.W_OK):
        raise OutputPathError(f"{flag} {file} is not writable; pass a file path you may write to")
    existing = _nearest_existing(file.parent)
    if not existing.is_dir():
        raise OutputPathError(f"{flag} {file} lies under {existing}, a file, not a folder; pass a path in a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputPathError(f"{flag} {file}: cannot write into {existing}; pass a file path you may write to")
