"""Benchmark workloads of :mod:`apps.bench`, one module per domain.

A workload is a function ``setup(device, size) -> Case`` registered under a name with
:func:`workload`; one registered with ``writes_images=True`` takes a third argument, ``images``: the folder its
images go to (``apps.bench --images``), or ``None`` for none. ``setup`` allocates everything; the returned
``Case.run`` does only the timed work, and ``Case.reference`` does the same work in pure torch/NumPy, timed in the
same run. A ``setup`` that lacks what it needs on this machine (a data file) raises :class:`WorkloadUnavailable`; the
suite then skips it and says why.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["SIZES", "Case", "Workload", "WorkloadUnavailable", "load_all", "workload"]

SIZES = ("smoke", "paper", "large")


class WorkloadUnavailable(RuntimeError):
    """A workload cannot run on this machine; the message names what is missing and how to provide it."""


@dataclass(frozen=True)
class Case:
    """One prepared workload.

    Attributes:
        run: the timed work (one repetition); must leave its result on the device.
        reference: the same work in pure torch/NumPy, or ``None`` when there is none.
        params: sizes and settings that define the work, written to the JSON record.
        work: amount of work one repetition does, in the numerator of ``unit``.
        unit: throughput unit, e.g. ``"GB/s"`` (then ``work`` is in GB), ``"Mpoints/s"``, ``"steps/s"``.
        bytes_moved: DRAM bytes one repetition must move, for the bandwidth roofline; ``None`` if
            the workload is not bandwidth-bound.
        flops: floating-point operations per repetition, for the compute roofline; ``None`` if the
            workload is not compute-bound.
        reference_name: what the reference is, for the table.
        extra: further figures to report (e.g. Newton iterations), written to the record.
        frame_seconds: simulated time one repetition advances, s, for a simulation that steps frame by frame; the
            record then carries ``realtime_factor = frame_seconds / median_s`` (above 1: faster than real time).
        observe: untimed work after every repetition (warm-up included), e.g. measuring the result with the
            project's own kernels into ``extra``; ``None`` when there is none.
    """

    run: Callable[[], object]
    reference: Callable[[], object] | None
    params: dict
    work: float
    unit: str
    bytes_moved: float | None = None
    flops: float | None = None
    reference_name: str = "torch"
    extra: dict = field(default_factory=dict)
    frame_seconds: float | None = None
    observe: Callable[[], object] | None = None


@dataclass(frozen=True)
class Workload:
    """A registered workload; ``writes_images``: its ``setup`` takes the images folder as a third argument."""

    name: str
    description: str
    setup: Callable[..., Case]
    writes_images: bool = False


REGISTRY: dict[str, Workload] = {}


def workload(name: str, description: str, writes_images: bool = False):
    """Register ``setup(device, size) -> Case`` (``setup(device, size, images)`` with ``writes_images``) as the
    workload ``name``."""

    def register(setup: Callable[..., Case]) -> Callable[..., Case]:
        if name in REGISTRY:
            raise ValueError(f"workload {name!r} is registered twice")
        REGISTRY[name] = Workload(name, description, setup, writes_images)
        return setup

    return register


def load_all() -> dict[str, Workload]:
    """Import every workload module of this package and return the registry, sorted by name."""
    for module in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{module.name}")
    return dict(sorted(REGISTRY.items()))
