"""Kernel benchmark suite.

    python -m apps.bench --list
    python -m apps.bench --workload copy_taichi,copy_warp --device cuda --size paper --json out/bench.json
    python -m apps.bench --workload nerf_train --device cuda --size paper --json out/nerf.json --images out/images

Each workload is warmed up, run ``--reps`` times with device synchronisation around every
repetition, and timed against its pure torch/NumPy reference in the same run. Records carry the
median, min and max, the throughput, the speed-up over the reference and, on CUDA, the fraction of
the GPU's memory-bandwidth or compute roofline. A readable table is printed; ``--json`` writes the
records. Workloads that show their results as images (``nerf_train``'s error maps) write them into a subfolder of
``--images``, or of ``<json stem>-images`` beside the ``--json`` file; with neither, no images are written.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from apps.workloads import SIZES, Case, WorkloadUnavailable, load_all
from kernels import backend
from pienerf.output_files import OutputPathError, check_output_file, check_output_folder, write_json

# Data-sheet peaks: DRAM bandwidth (bytes/s) and dense FP32 non-tensor-core throughput (FLOP/s).
GPU_PEAKS = {
    "H100": {"bandwidth": 3.35e12, "fp32": 67e12},
    "H200": {"bandwidth": 4.8e12, "fp32": 67e12},
    "A100": {"bandwidth": 2.0e12, "fp32": 19.5e12},
}
DEFAULT_REPS = {"smoke": 3, "paper": 10, "large": 5}
MAX_REPS = 10_000
"""Most timed repetitions ``--reps`` may ask for."""
REFERENCE_BUDGET_S = 20.0


def gpu_peaks() -> dict | None:
    """Peaks of the current GPU from :data:`GPU_PEAKS`, or ``None`` when it is not in the table."""
    name = torch.cuda.get_device_name(0)
    return next((peaks for key, peaks in GPU_PEAKS.items() if key in name), None)


def time_repetitions(fn, reps: int, budget_s: float = math.inf, after=None) -> list[float]:
    """Seconds of each of ``reps`` synchronised runs of ``fn`` after one warm-up run.

    Stops early once ``budget_s`` (which counts ``after`` too) is spent and at least three runs are timed.
    ``after``, when given, is called untimed after every run, the warm-up included.
    """
    fn()
    backend.synchronize()
    if after is not None:
        after()
    times: list[float] = []
    start_all = time.perf_counter()
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        backend.synchronize()
        times.append(time.perf_counter() - start)
        if after is not None:
            after()
        if len(times) >= 3 and time.perf_counter() - start_all > budget_s:
            break
    return times


def measure(name: str, case: Case, device: str, size: str, reps: int) -> dict:
    """Time one prepared case and its reference; return the JSON record."""
    times = time_repetitions(case.run, reps, after=case.observe)
    median = statistics.median(times)
    record = {
        "workload": name,
        "device": device,
        "device_name": torch.cuda.get_device_name(0) if device == "cuda" else _cpu_name(),
        "size": size,
        "params": case.params,
        "median_s": median,
        "min_s": min(times),
        "max_s": max(times),
        "reps": len(times),
        "throughput": case.work / median,
        "unit": case.unit,
        "reference": case.reference_name if case.reference else None,
        "reference_median_s": None,
        "speedup_vs_reference": None,
        **case.extra,
    }
    if case.frame_seconds is not None:
        record["realtime_factor"] = case.frame_seconds / median
    if case.reference is not None:
        ref_times = time_repetitions(case.reference, reps, budget_s=REFERENCE_BUDGET_S)
        record["reference_median_s"] = statistics.median(ref_times)
        record["speedup_vs_reference"] = record["reference_median_s"] / median
    if device == "cuda":
        peaks = gpu_peaks()
        if peaks and case.bytes_moved:
            record["achieved_bandwidth_tbs"] = case.bytes_moved / median / 1e12
            record["roofline_fraction"] = case.bytes_moved / median / peaks["bandwidth"]
            record["roofline"] = f"memory {peaks['bandwidth'] / 1e12:.2f} TB/s"
        elif peaks and case.flops:
            record["roofline_fraction"] = case.flops / median / peaks["fp32"]
            record["roofline"] = f"fp32 {peaks['fp32'] / 1e12:.1f} TFLOP/s"
    return record


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} threads)"
    except OSError:
        pass
    return f"cpu ({os.cpu_count()} threads)"


def print_table(records: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="benchmark (median of reps)")
    for column in ("workload", "device", "size", "median", "throughput", "reference", "speed-up", "roofline"):
        table.add_column(column, justify="left" if column in ("workload", "reference") else "right")
    for r in records:
        ref = f"{r['reference']} {_ms(r['reference_median_s'])}" if r["reference"] else "-"
        speedup = f"{r['speedup_vs_reference']:.2f}x" if r["speedup_vs_reference"] else "-"
        roof = f"{100 * r['roofline_fraction']:.1f}% of {r['roofline']}" if "roofline_fraction" in r else "-"
        table.add_row(
            r["workload"], r["device"], r["size"], _ms(r["median_s"]),
            f"{r['throughput']:.4g} {r['unit']}", ref, speedup, roof,
        )
    Console(width=max(140, Console().width)).print(table)


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3f} ms"


def _fail(message: str) -> None:
    print(f"bench: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m apps.bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--list", action="store_true", help="list the workloads and exit")
    parser.add_argument("--workload", default="all", help="comma-separated workload names, or 'all'")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    parser.add_argument("--size", default="smoke", help="smoke, paper or large")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (default by size)")
    parser.add_argument("--json", type=Path, default=None, help="write the records to this file")
    parser.add_argument(
        "--images", type=Path, default=None,
        help="folder for the images some workloads write (default: <json stem>-images beside --json, else none)",
    )
    args = parser.parse_args(argv)

    registry = load_all()
    if args.list:
        for w in registry.values():
            print(f"{w.name:24s} {w.description}")
        return []

    names = list(registry) if args.workload == "all" else [n.strip() for n in args.workload.split(",") if n.strip()]
    unknown = [n for n in names if n not in registry]
    if unknown or not names:
        _fail(f"unknown workload {', '.join(map(repr, unknown)) or repr(args.workload)}; valid: {', '.join(registry)}")
    if args.size not in SIZES:
        _fail(f"unknown size {args.size!r}; valid: {', '.join(SIZES)}")
    if args.reps is not None and not 1 <= args.reps <= MAX_REPS:
        _fail(f"--reps must be between 1 and {MAX_REPS}, got {args.reps}")
    images = args.images
    if images is None and args.json is not None:
        images = args.json.with_name(f"{args.json.stem}-images")
    try:
        if args.json is not None:
            check_output_file(args.json, "--json")
        if images is not None and any(registry[n].writes_images for n in names):
            check_output_folder(images, "--images")
    except OutputPathError as error:
        _fail(str(error))
    try:
        device = backend.init(args.device)
    except (ValueError, RuntimeError) as error:
        _fail(str(error))

    reps = DEFAULT_REPS[args.size] if args.reps is None else args.reps
    records = []
    for i, name in enumerate(names, 1):
        print(f"[{i}/{len(names)}] {name} on {device} ({args.size})", file=sys.stderr, flush=True)
        try:
            entry = registry[name]
            case = entry.setup(device, args.size, images) if entry.writes_images else entry.setup(device, args.size)
        except WorkloadUnavailable as reason:
            print(f"[{i}/{len(names)}] {name} skipped: {reason}", file=sys.stderr, flush=True)
            continue
        records.append(measure(name, case, device, args.size, reps))
        del case
    print_table(records)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, records)
        print(f"wrote {args.json}", file=sys.stderr)
    return records


if __name__ == "__main__":
    main()
