"""Start-up time of NeRF training: seconds from the start of this process to the end of its first training step.

    python -m apps.nerf_startup --device cuda --size paper
    python -m apps.nerf_startup --device cpu --size smoke --dataset ../shared/data/nerf_synthetic_lego

Imports the project, initialises the backend, loads the training views, builds the field and the
:class:`~pienerf.nerf.Trainer` of ``nerf_train`` at that size (:func:`apps.workloads.nerf.nerf_setup`) and runs one
step, then prints one JSON line: ``first_step_s`` (seconds since the process started, from the kernel's process
table, so the interpreter's own start counts) and ``breakdown``, the seconds of each phase (``interpreter``: process
start to this module's first line; ``imports``; ``backend_init``; ``data``; ``field``; ``trainer``; ``first_step``,
synchronised). ``nerf_train`` runs it twice at paper size (the second with warm kernel caches) through
:func:`apps.workloads.nerf.measure_startup`.
"""

import time

_MODULE_START = time.perf_counter()  # before the imports this program measures

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from apps.workloads.nerf import LEGO, nerf_setup  # noqa: E402
from kernels import backend  # noqa: E402
from pienerf.nerf.datasets import load_nerf_dataset  # noqa: E402
from pienerf.nerf.field import NGPField  # noqa: E402
from pienerf.nerf.training import Trainer, start_optimizer_import  # noqa: E402

_IMPORTS_DONE = time.perf_counter()


def process_age_s() -> float:
    """Seconds since this process started, from ``/proc`` (start time and uptime share the kernel's clock, 10 ms
    ticks), so that the interpreter's start-up counts too.

    Raises:
        RuntimeError: no ``/proc`` (not Linux).
    """
    try:
        stat = Path("/proc/self/stat").read_text()
        uptime = float(Path("/proc/uptime").read_text().split()[0])
    except OSError as error:
        raise RuntimeError(f"the start-up probe reads /proc (Linux only): {error}") from error
    start_ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22, counted after the parenthesised name
    return uptime - start_ticks / os.sysconf("SC_CLK_TCK")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m apps.nerf_startup", description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=backend.DEVICES, default=None, help="default: cuda when present")
    parser.add_argument("--size", choices=("smoke", "paper", "large"), default="paper", help="nerf_train's sizes")
    parser.add_argument("--dataset", type=Path, default=LEGO, help="NeRF-synthetic folder (default: the lego)")
    parser.add_argument("--downscale", type=int, default=1, help="integer image downscale (smoke runs)")
    parser.add_argument("--max-views", type=int, default=None, help="read only the first views (smoke runs)")
    args = parser.parse_args(argv)

    phases = {"imports": _IMPORTS_DONE - _MODULE_START}
    start_optimizer_import()  # overlaps with what follows (pienerf.nerf.training)
    start = time.perf_counter()
    backend.init(args.device)
    phases["backend_init"] = time.perf_counter() - start
    start = time.perf_counter()
    try:
        views = load_nerf_dataset(args.dataset, "train", args.downscale, (0.0, 0.0, 0.0), args.max_views)
    except (FileNotFoundError, ValueError) as error:
        print(f"nerf_startup: error: {error}", file=sys.stderr)
        raise SystemExit(2) from error
    train = views.held_out(8)[0] if len(views) >= 8 else views
    phases["data"] = time.perf_counter() - start
    start = time.perf_counter()
    config, aabb, train_config = nerf_setup(args.size)
    field = NGPField(config, aabb)
    phases["field"] = time.perf_counter() - start
    start = time.perf_counter()
    trainer = Trainer(field, train, train_config)
    phases["trainer"] = time.perf_counter() - start
    start = time.perf_counter()
    trainer.train_step()
    backend.synchronize()
    phases["first_step"] = time.perf_counter() - start
    total = process_age_s()
    report = {
        "first_step_s": total,
        "breakdown": {"interpreter": total - (time.perf_counter() - _MODULE_START), **phases},
        "device": backend.current_device(),
        "views": len(train),
        "image_size": [train.cameras.width, train.cameras.height],
    }
    print(json.dumps(report), flush=True)
    return report


if __name__ == "__main__":
    main()
