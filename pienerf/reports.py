"""Reports of a simulation run: the per-step time breakdown (PIE-NeRF Fig. 10) and the volume of the
body over time (Fig. 6), as numbers and as images (each written whole or not at all)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from pienerf.output_files import atomic_path, write_json
from pienerf.sim.solver import QGMLSStepReport

__all__ = ["TimeBreakdown", "VolumeHistory", "plot_time_breakdown", "plot_volume_bars"]


@dataclass
class TimeBreakdown:
    """Accumulated seconds per phase of the run: the steps' :attr:`STEP_PHASES`; warping and others where rendered
    (:meth:`add_phase`); ``"device loop"`` for device-loop steps not timed by phase
    (:meth:`pienerf.sim.solver.SolverQGMLS.step` with ``timed=False``), each charged as a whole.

    The JSON (:meth:`to_dict`) keeps the earlier keys: a breakdown written before the line search was a phase of its
    own has no ``"line search"`` (its line search is in ``"other"``); readers take a missing phase as 0.
    """

    STEP_PHASES: ClassVar[tuple[str, ...]] = ("assembly", "solve", "line search", "other")
    """The phases of a solver step (``QGMLSStepReport.time_assembly``, ``time_solve``, ``time_line_search``,
    ``time_other``)."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TimeBreakdown.STEP_PHASES, 0.0))
    steps: int = 0
    newton_iterations: int = 0

    def add(self, report: QGMLSStepReport) -> None:
        """Accumulate one :class:`QGMLSStepReport`: its phases where timed (a timed device-loop step's time outside
        its phases, the wall time less their sum, to ``"other"``), else its whole time to ``"device loop"``."""
        if report.timed:
            self.seconds["assembly"] += report.time_assembly
            self.seconds["solve"] += report.time_solve
            self.seconds["line search"] = self.seconds.get("line search", 0.0) + report.time_line_search
            self.seconds["other"] += report.time_other
            if report.device_loop:
                phases = report.time_assembly + report.time_solve + report.time_line_search + report.time_other
                self.seconds["other"] += max(report.time_device_loop - phases, 0.0)
        else:  # the phases ran as one graph, timed as a whole
            self.add_phase("device loop", report.time_device_loop)
        self.steps += 1
        self.newton_iterations += report.iterations

    def add_phase(self, name: str, seconds: float) -> None:
        """Accumulate time of another phase (e.g. ``"quadratic warping"``)."""
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def fractions(self) -> dict[str, float]:
        """Share of the total per phase."""
        total = sum(self.seconds.values()) or 1.0
        return {name: value / total for name, value in self.seconds.items()}

    def to_dict(self) -> dict:
        per_step = {name: value / max(self.steps, 1) for name, value in self.seconds.items()}
        return {
            "steps": self.steps,
            "newton_iterations": self.newton_iterations,
            "seconds": self.seconds,
            "seconds_per_step": per_step,
            "fractions": self.fractions(),
        }


@dataclass
class VolumeHistory:
    """Volume of the deformed body (m³) at labelled instants, e.g. compression ratios."""

    rest_volume: float
    labels: list[str] = field(default_factory=list)
    volumes: list[float] = field(default_factory=list)

    def add(self, label: str, volume: float) -> None:
        self.labels.append(label)
        self.volumes.append(float(volume))

    def relative(self) -> np.ndarray:
        """Volumes divided by the rest volume."""
        return np.asarray(self.volumes) / self.rest_volume


def plot_time_breakdown(breakdown: TimeBreakdown, path: Path | str, title: str = "time per step") -> Path:
    """Pie chart of the time breakdown (Fig. 10) written to ``path`` (PNG), with a JSON beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [name for name, value in breakdown.seconds.items() if value > 0]
    values = [breakdown.seconds[name] for name in names]
    per_step_ms = 1e3 * sum(values) / max(breakdown.steps, 1)
    fig, ax = plt.subplots(figsize=(5, 4), dpi=120)
    ax.pie(values, labels=names, autopct="%1.1f%%", startangle=90, counterclock=False)
    ax.set_title(f"{title}: {per_step_ms:.1f} ms/step over {breakdown.steps} steps")
    fig.tight_layout()
    try:
        with atomic_path(path) as temporary:
            fig.savefig(temporary)
    finally:
        plt.close(fig)
    write_json(path.with_suffix(".json"), breakdown.to_dict())
    return path


def plot_volume_bars(histories: Sequence[tuple[str, VolumeHistory]], path: Path | str) -> Path:
    """Grouped bars of relative volume per instant for several runs (Fig. 6, bottom), as PNG + JSON.

    Each bar is written with its value; a plot with no samples says so in the image instead of staying blank.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not histories:
        raise ValueError("plot_volume_bars needs at least one (name, VolumeHistory); pass the runs' histories")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = histories[0][1].labels
    width = 0.8 / len(histories)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    for i, (name, history) in enumerate(histories):
        x = np.arange(len(history.labels)) + (i - (len(histories) - 1) / 2) * width
        bars = ax.bar(x, history.relative(), width, label=name)
        ax.bar_label(bars, fmt="%.3f", fontsize=7)
    ax.axhline(1.0, color="black", linewidth=0.8)
    ax.set_xticks(np.arange(len(labels)), labels)
    ax.set_ylabel("volume / rest volume")
    ax.set_ylim(0.0, 1.2)
    if any(len(history.labels) for _, history in histories):
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no volume samples were taken in this run", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    try:
        with atomic_path(path) as temporary:
            fig.savefig(temporary)
    finally:
        plt.close(fig)
    data = {name: {"labels": h.labels, "relative_volume": h.relative().tolist()} for name, h in histories}
    write_json(path.with_suffix(".json"), data)
    return path
