"""Independent runs as tasks of one executor: in this process one after another (``local``), or as Ray tasks on one
machine or a cluster of them (``ray``, the optional extra ``pip install -e '.[cluster]'``).

A sweep's points (:mod:`pienerf.scenario.sweep`) and a batch's avatars (:mod:`physavatar.pipeline.batch`) are both
*points*: a name, a table of JSON-ready parameters, and one call of a point function
``function(parameters, folder) -> metrics`` that writes its results into ``folder`` and returns a JSON-ready table of
what it measured. :func:`run_points` runs every point and writes, under the root folder:

* ``NAME/`` per point, written whole or not at all (:func:`pienerf.output_files.staged_folder`): a point killed
  part way leaves nothing at ``NAME/``, and its ``point.json`` records its parameters, metrics, status and timing;
* ``INDEX.json`` and ``INDEX.csv`` (``sweep`` or ``batch``): one row per point with its parameters, its status
  (``complete``, ``failed``, ``skipped``), the error of a failed one and, flattened, its metrics; rewritten after
  every point that ends, so an interrupted run leaves an index of the points that finished.

A point that raises, or whose worker process dies, is retried ``max_retries`` times (Ray's ``max_retries`` with
``retry_exceptions``; the same count in-process for an exception) and then recorded as failed with its error; the
other points go on. A rerun skips every point whose ``NAME/point.json`` is complete with the same parameters
(resume); any other point runs again. Progress is a line whenever a point starts or ends: points done, running,
failed, waiting.

Under Ray the points run on a pool of actors, one per GPU on CUDA (Ray shows each only its GPU, for its whole life)
or one per ``cpus_per_point`` cores on a CPU, each handed the next waiting point as it finishes one, so a worker's
imports, CUDA context and kernel loads are paid once per actor rather than once per point. The root folder must be
one every worker can write (one machine, or a shared file system).
Ray is started here when no cluster is given (``address`` or ``$RAY_ADDRESS``), announced as 127.0.0.1 with no
dashboard (its processes still listen on every interface: Ray has no setting to bind them to one), and shut down
after the run; a cluster, or a Ray already started in this process, is left running.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import socket
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from pienerf.output_files import atomic_path, staged_folder, stale_staging_folders, write_json

__all__ = [
    "EXECUTORS",
    "POINT_FILE",
    "ExecutorConfig",
    "ExecutorError",
    "PointFunction",
    "completed_point",
    "flatten",
    "require_ray",
    "run_points",
    "write_index",
]

EXECUTORS = ("local", "ray")
"""The executors: ``local`` runs the points in this process one after another; ``ray`` runs each as a Ray task."""

POINT_FILE = "point.json"
"""The record of one point in its folder: name, parameters, status, metrics, timing, host."""

_ATTEMPTS = ".attempts"
"""Folder under the root holding one log per point, a line per attempt started (run id, host, process id)."""

PointFunction = Callable[[dict, Path], dict]
"""``function(parameters, folder) -> metrics``: one point's work, its results written into ``folder`` (which exists
and is empty), its measurements returned as a JSON-ready table. Under Ray it is pickled to the workers: a
module-level function or a :func:`functools.partial` of one, from a module the workers can import."""


class ExecutorError(RuntimeError):
    """The executor cannot run: Ray is not installed, or the cluster cannot be reached; the message names the fix."""


@dataclass(frozen=True)
class ExecutorConfig:
    """How the points run.

    Attributes:
        kind: ``"local"`` or ``"ray"`` (:data:`EXECUTORS`).
        device: ``"cpu"`` or ``"cuda"``: under Ray a CUDA point asks for one GPU, a CPU point for ``cpus_per_point``.
        address: the Ray cluster to join (``ray://`` or ``host:port``), else ``$RAY_ADDRESS``, else a Ray started on
            this machine for the run.
        max_retries: attempts after the first for a point that raised or whose worker died.
        cpus_per_point: CPU cores one point asks Ray for (``None``: one on a CPU; on CUDA the cluster's cores per GPU,
            so that a point's torch and Taichi threads are not cut to the one core Ray gives by default).
        local_cpus: cores of the Ray started on this machine (``None``: all of them).
    """

    kind: str = "local"
    device: str = "cpu"
    address: str | None = None
    max_retries: int = 2
    cpus_per_point: float | None = None
    local_cpus: int | None = None

    def __post_init__(self):
        if self.kind not in EXECUTORS:
            raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {self.kind!r}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        if not (isinstance(self.max_retries, int) and 0 <= self.max_retries <= 100):
            raise ValueError(f"max_retries (--retries) must be an integer in [0, 100], got {self.max_retries!r}")
        if self.cpus_per_point is not None and not (math.isfinite(self.cpus_per_point) and self.cpus_per_point > 0):
            raise ValueError(f"cpus_per_point must be a positive number of cores, got {self.cpus_per_point!r}")


def require_ray():
    """The ``ray`` module.

    Raises:
        ExecutorError: Ray is not installed; the message says how to install it.
    """
    try:
        import ray  # deferred: Ray is an optional extra, imported only by the ray executor
    except ModuleNotFoundError:
        raise ExecutorError(
            "--executor ray needs Ray, which is not installed: pip install -e '.[cluster]' (or pip install "
            "ray==2.58.0), or run with --executor local"
        ) from None
    return ray


def completed_point(folder: Path, parameters: dict) -> dict | None:
    """The record of a point already complete in ``folder`` with these ``parameters``, or ``None``: the folder is
    absent, its ``point.json`` unreadable, failed, or for other parameters."""
    try:
        record = json.loads((Path(folder) / POINT_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("status") != "complete":
        return None
    if record.get("parameters") != json.loads(json.dumps(parameters)):
        return None
    return record


def _log_attempt(root: Path, name: str, run_id: str) -> int:
    """Append this attempt to the point's attempt log; returns the attempts of this run so far, this one included."""
    log = root / _ATTEMPTS / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as file:
        file.write(f"{run_id} {socket.gethostname()} {os.getpid()} {time.time():.3f}\n")
    return _attempts(root, name, run_id)


def _attempts(root: Path, name: str, run_id: str) -> int:
    try:
        lines = (root / _ATTEMPTS / f"{name}.log").read_text().splitlines()
    except OSError:
        return 0
    return sum(line.split(" ", 1)[0] == run_id for line in lines)


def _run_point(function: PointFunction, name: str, parameters: dict, root: str, run_id: str) -> dict:
    """One attempt at one point, in whichever process runs it: its folder staged whole, then its record.

    Raises whatever the point function raises (the folder is then left as it was): the executor retries it.
    """
    root = Path(root)
    attempt = _log_attempt(root, name, run_id)
    for stale in stale_staging_folders(root / name):  # an earlier attempt's, killed part way
        shutil.rmtree(stale, ignore_errors=True)
    started = time.time()
    clock = time.perf_counter()
    with staged_folder(root / name) as folder:
        metrics = function(dict(parameters), folder)
        record = {
            "name": name,
            "parameters": parameters,
            "status": "skipped" if isinstance(metrics, dict) and metrics.get("skipped") else "complete",
            "metrics": metrics,
            "error": None,
            "attempts": attempt,
            "seconds": time.perf_counter() - clock,
            "started": started,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "gpus": os.environ.get("CUDA_VISIBLE_DEVICES"),  # under Ray, the GPU it gave this point's actor
        }
        write_json(folder / POINT_FILE, record, default=str)
    return record


def _failed(name: str, parameters: dict, error: BaseException, attempts: int) -> dict:
    return {
        "name": name,
        "parameters": parameters,
        "status": "failed",
        "metrics": {},
        "error": _error_text(error),
        "attempts": attempts,
        "seconds": None,
    }


def _error_text(error: BaseException) -> str:
    """The last line of a point's error: Ray wraps an exception in a traceback of the worker."""
    cause = getattr(error, "cause", None)
    if isinstance(cause, BaseException):
        error = cause
    text = f"{type(error).__name__}: {error}".strip()
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[-1] if len(lines) > 1 and "Traceback" in text else text


def flatten(value, prefix: str = "") -> dict:
    """A nested table as one level of ``a.b.c`` keys, lists of numbers kept as JSON text (the CSV's columns)."""
    if isinstance(value, dict):
        flat = {}
        for key, item in value.items():
            flat.update(flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    if isinstance(value, (list, tuple)):
        return {prefix: json.dumps(value, default=str)}
    return {prefix: value}


def write_index(root: Path, index: str, entries: list[dict], extra: dict | None = None) -> tuple[Path, Path]:
    """Write ``INDEX.json`` (every point's record, and ``extra``) and ``INDEX.csv`` (one row per point: name, status,
    attempts, seconds, error, ``parameter.*`` and ``metric.*`` columns) under ``root``, each atomically."""
    root = Path(root)
    counts = {status: sum(e["status"] == status for e in entries) for status in ("complete", "failed", "skipped")}
    write_json(root / f"{index}.json", {**(extra or {}), "counts": counts, "points": entries}, default=str)
    rows, columns = [], ["name", "status", "attempts", "seconds", "error"]
    for entry in entries:
        row = {key: entry.get(key) for key in columns}
        row.update(flatten(entry.get("parameters", {}), "parameter"))
        row.update(flatten(entry.get("metrics", {}), "metric"))
        rows.append(row)
        columns += [key for key in row if key not in columns]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    csv_path = root / f"{index}.csv"
    with atomic_path(csv_path) as temporary:
        temporary.write_text(text.getvalue())
    return root / f"{index}.json", csv_path


class _Progress:
    """Counts of the points, said in one line whenever they change."""

    def __init__(self, label: str, total: int, log: Callable[[str], None]):
        self.label, self.total, self.log = label, total, log
        self.done = self.failed = self.resumed = self.running = 0
        self._last = None

    def say(self, event: str = "") -> None:
        waiting = self.total - self.done - self.failed - self.resumed - self.running
        line = (
            f"{self.label}: {self.done + self.resumed}/{self.total} done ({self.resumed} already complete), "
            f"{self.running} running, {self.failed} failed, {waiting} waiting"
        )
        if line != self._last or event:
            self.log(line + (f" — {event}" if event else ""))
            self._last = line


def run_points(
    points: dict[str, dict],
    function: PointFunction,
    root: Path | str,
    config: ExecutorConfig = ExecutorConfig(),
    index: str = "sweep",
    log: Callable[[str], None] = print,
    extra: dict | None = None,
) -> list[dict]:
    """Run every point not already complete under ``root`` and write the index; returns the points' records in the
    order of ``points`` (see the module docstring).

    Args:
        points: point name (its folder under ``root``: letters, digits, ``_``, ``-``) → its parameters (JSON-ready).
        function: the point function, called once per attempt with ``(parameters, folder)``.
        root: the folder of the points and the index.
        config: the executor, device and retries.
        index: the index files' stem (``sweep`` or ``batch``).
        log: where the progress lines go.
        extra: more of ``INDEX.json`` (what was swept, the base scenario, the executor).

    Raises:
        ExecutorError: ``config.kind == "ray"`` and Ray is missing or its cluster cannot be reached.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    run_id = uuid.uuid4().hex[:12]
    records: dict[str, dict] = {}
    progress = _Progress(index, len(points), log)
    todo = {}
    for name, parameters in points.items():
        record = completed_point(root / name, parameters)
        if record is not None:
            records[name] = {**record, "skipped_as_complete": True}
            progress.resumed += 1
        else:
            todo[name] = parameters
    extra = {**(extra or {}), "executor": config.kind, "device": config.device, "max_retries": config.max_retries}

    def finish(name: str, record: dict) -> None:
        records[name] = record
        write_index(root, index, [records[n] for n in points if n in records], extra)

    progress.say()
    if config.kind == "local":
        _run_local(todo, function, root, config, run_id, progress, finish)
    else:
        _run_ray(todo, function, root, config, run_id, progress, finish)
    entries = [records[n] for n in points]
    write_index(root, index, entries, extra)
    return entries


def _run_local(todo, function, root, config, run_id, progress, finish) -> None:
    for name, parameters in todo.items():
        progress.running = 1
        progress.say(f"{name} started")
        for attempt in range(config.max_retries + 1):
            try:
                record = _run_point(function, name, parameters, str(root), run_id)
                progress.done += 1
                break
            except Exception as error:  # a point's failure is recorded, the sweep goes on
                if attempt < config.max_retries:
                    progress.log(f"{name}: attempt {attempt + 1} failed ({_error_text(error)}); retrying")
                    continue
                traceback.print_exc()
                record = _failed(name, parameters, error, _attempts(root, name, run_id))
                progress.failed += 1
        progress.running = 0
        finish(name, record)
        progress.say(f"{name} {record['status']}")


def _start_ray(ray, config: ExecutorConfig) -> bool:
    """Connect to the cluster or start a local Ray, unless this process already has; returns whether this call
    started it (and so shuts it down).

    Raises:
        ExecutorError: the cluster cannot be reached or started, or a CUDA run finds no GPU in it.
    """
    started = not ray.is_initialized()
    if started:
        address = config.address or os.environ.get("RAY_ADDRESS")
        try:
            if address:
                ray.init(address=address, log_to_driver=True)
            else:
                ray.init(
                    num_cpus=config.local_cpus,
                    # the GPUs torch sees (CUDA_VISIBLE_DEVICES honoured), so a CUDA point's num_gpus=1 can be met
                    num_gpus=torch.cuda.device_count() if config.device == "cuda" else None,
                    include_dashboard=False,
                    _node_ip_address="127.0.0.1",
                    log_to_driver=True,
                )
        except (ConnectionError, RuntimeError, ValueError) as error:
            where = f"the Ray cluster at {address}" if address else "a local Ray"
            raise ExecutorError(
                f"could not start or join {where} ({error}); check the address (ray start --head prints it) or "
                "leave --ray-address and RAY_ADDRESS unset to start Ray on this machine"
            ) from None
    if config.device == "cuda" and ray.cluster_resources().get("GPU", 0) < 1:
        if started:
            ray.shutdown()
        raise ExecutorError(
            "the Ray cluster has no GPU, so no CUDA point could ever start; start its nodes with GPUs "
            "(ray start --num-gpus N) or run with --device cpu"
        )
    return started


class _PointRunner:
    """A Ray actor that runs points one after another in one worker process: the process's imports, CUDA context and
    kernel loads are paid once, and the GPU Ray gives it is its own for its whole life (a reused Ray *task* worker may
    be handed another GPU than the one its CUDA context was made on, and two points then share one GPU)."""

    def run(self, function: PointFunction, name: str, parameters: dict, root: str, run_id: str) -> dict:
        return _run_point(function, name, parameters, root, run_id)


def _ray_resources(ray, config: ExecutorConfig) -> dict:
    """What one point's runner asks Ray for: ``cpus_per_point`` cores (:class:`ExecutorConfig`), and one GPU on
    CUDA. Ray sets a runner's ``OMP_NUM_THREADS`` to its cores."""
    if config.device != "cuda":
        return {"num_cpus": config.cpus_per_point or 1.0}
    cluster = ray.cluster_resources()
    share = max(1, int(cluster.get("CPU", 1) // max(cluster.get("GPU", 1), 1)))
    return {"num_gpus": 1, "num_cpus": config.cpus_per_point or share}


def _run_ray(todo, function, root, config, run_id, progress, finish) -> None:
    """The points on a pool of :class:`_PointRunner` actors, as many as the cluster holds at once (one per GPU on
    CUDA), each handed the next waiting point when it finishes one. A point that raises, or whose runner dies (Ray
    restarts the runner), goes back to the front of the queue until its retries are spent."""
    ray = require_ray()
    started = _start_ray(ray, config)
    actors = []
    try:
        resources = _ray_resources(ray, config)
        unit = "GPU" if config.device == "cuda" else "CPU"
        per_runner = resources.get("num_gpus", resources["num_cpus"])
        slots = max(1, min(len(todo), int(ray.cluster_resources().get(unit, 1) // per_runner)))
        runner = ray.remote(max_restarts=-1, **resources)(_PointRunner)
        actors = [runner.remote() for _ in range(slots)] if todo else []
        queue, idle, pending = list(todo), list(actors), {}
        tries = dict.fromkeys(todo, 0)
        while queue or pending:
            while queue and idle:
                name, actor = queue.pop(0), idle.pop(0)
                tries[name] += 1
                pending[actor.run.remote(function, name, todo[name], str(root), run_id)] = (name, actor)
            progress.running = len(pending)
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=2.0)
            for ref in ready:
                name, actor = pending.pop(ref)
                idle.append(actor)
                try:
                    record = ray.get(ref)
                    progress.done += 1
                except Exception as error:  # a raise, or the runner's process died: retried, then recorded
                    if tries[name] <= config.max_retries:
                        progress.log(f"{name}: attempt {tries[name]} failed ({_error_text(error)}); retrying")
                        queue.insert(0, name)
                        continue
                    record = _failed(name, todo[name], error, _attempts(root, name, run_id))
                    progress.failed += 1
                progress.running = len(pending)
                finish(name, record)
                progress.say(f"{name} {record['status']}")
            if not ready:
                progress.say()
    finally:
        if started:
            ray.shutdown()
        else:  # a cluster outlives the run: its runners do not
            for actor in actors:
                ray.kill(actor, no_restart=True)
