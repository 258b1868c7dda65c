"""The resolution a viewer renders a preview at: coarse while the body or the camera moves, as far as a frame budget
asks, full once still (:class:`RefinementSchedule`)."""

from __future__ import annotations

import math

import torch

__all__ = ["RefinementSchedule"]


class RefinementSchedule:
    """The resolution a preview is rendered at: coarse enough to hold a frame budget while the body or the camera
    moves, full once still.

    While things move, the schedule picks the finest integer downscale in ``[still, max_downscale]`` whose
    predicted render time plus the last simulation step's time fits ``frame_budget``. The viewer reports each
    render with :meth:`record`; the schedule keeps an exponential moving average of the render time at every
    level it has seen and fits ``t(level) = a + c / level²`` to them (least squares, ``a, c >= 0``): ``a`` the cost
    of a render whatever its size (set-up, encoding, sending), ``c`` the cost of the full-resolution pixels. With one
    level seen, ``a = 0``. When no level fits, it takes the finest level within ``overrun`` of the coarsest one's
    time: where the fixed cost dominates, a coarser image would cost sharpness and gain no frames (on an H100 the
    viewer's NeRF frame at 640 × 480 was bound by such costs at every level from 4 to 8). The level changes only
    when the prediction at the current one misses the budget by more than ``overrun`` or leaves more than ``slack``
    of it unused, so a prediction that hovers at the budget keeps the level. Until a render has been measured (the
    first one of a schedule is not: it pays one-off costs such as kernel compilation), it renders at ``moving``.
    Once still, it renders once at ``still``, then nothing.

    Args:
        moving: downscale while things move until the render cost is known: the start level. It is also the
            fixed moving level of the schedule when the viewer never calls :meth:`record`.
        still: downscale of the refined image.
        tolerance: generalized coordinates that changed less than this (m) since the last render count as still.
        frame_budget: seconds one frame may take, the simulation step and the render together (1/30: 30 frames
            per second).
        max_downscale: the coarsest downscale while moving.
        overrun: share of the budget the prediction may exceed before the level gets coarser.
        slack: share of the budget the prediction may leave unused before the level gets finer.
        smoothing: weight of the newest render in the moving average of the cost, in (0, 1].
    """

    def __init__(
        self,
        moving: int = 4,
        still: int = 1,
        tolerance: float = 1e-4,
        *,
        frame_budget: float = 1.0 / 30.0,
        max_downscale: int = 8,
        overrun: float = 0.15,
        slack: float = 0.3,
        smoothing: float = 0.3,
    ):
        for name, value in (("moving", moving), ("still", still), ("max_downscale", max_downscale)):
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{name} must be an integer downscale >= 1, got {value!r}")
        if not still <= moving <= max_downscale:
            raise ValueError(
                f"the downscales must satisfy still <= moving <= max_downscale, got {still}, {moving}, "
                f"{max_downscale}; raise max_downscale or lower moving"
            )
        self.frame_budget = self.check_frame_budget(frame_budget)
        for name, value, hi in (("overrun", overrun, math.inf), ("slack", slack, 1.0), ("smoothing", smoothing, 1.0)):
            if not (isinstance(value, (int, float)) and 0.0 < value <= hi):
                raise ValueError(f"{name} must be a number in (0, {hi:g}], got {value!r}")
        self.moving, self.still, self.tolerance, self.max_downscale = moving, still, tolerance, max_downscale
        self.overrun, self.slack, self.smoothing = float(overrun), float(slack), float(smoothing)
        self._q: torch.Tensor | None = None
        self._camera = None
        self._level: int | None = None
        self._moving_level = moving
        self._renders = 0
        self._seconds_at: dict[int, float] = {}  # moving average of the render time at each level seen, s
        self.fixed_cost: float | None = None
        """``a`` of the fitted render time ``a + c / level²`` (s), ``None`` until a render is measured."""
        self.full_cost: float | None = None
        """``c`` of the fitted render time: the pixels of a full-resolution render (s), ``None`` until measured."""
        self.last_step_seconds = 0.0
        """The last simulation step's time (s), as :meth:`record` was told."""

    @staticmethod
    def check_frame_budget(seconds: float) -> float:
        """``seconds`` as a float when it is a usable frame budget (positive, finite), else a ValueError."""
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0.0 < seconds < math.inf:
            raise ValueError(
                f"frame_budget must be a positive number of seconds, e.g. 1/30 for 30 frames per second, "
                f"got {seconds!r}"
            )
        return float(seconds)

    def predicted_seconds(self, level: int) -> float | None:
        """Predicted seconds of a frame rendered at downscale ``level``: the step plus the render, or ``None``
        while no render has been measured."""
        if self.full_cost is None or self.fixed_cost is None:
            return None
        return self.last_step_seconds + self.fixed_cost + self.full_cost / level**2

    def record(self, level: int, render_seconds: float, step_seconds: float = 0.0) -> None:
        """Learn from one render: it took ``render_seconds`` (s) at downscale ``level``, in a frame whose
        simulation step took ``step_seconds`` (s; 0 when the simulation is paused)."""
        if not (isinstance(level, int) and not isinstance(level, bool) and level >= 1):
            raise ValueError(f"level must be the integer downscale the render used, got {level!r}")
        for name, value in (("render_seconds", render_seconds), ("step_seconds", step_seconds)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < math.inf:
                raise ValueError(f"{name} must be a finite number of seconds >= 0, got {value!r}")
        self.last_step_seconds = float(step_seconds)
        self._renders += 1
        if self._renders == 1:  # the first render pays one-off costs (compilation, caches): not a measure
            return
        seconds = float(render_seconds)
        average = self._seconds_at.get(level)
        self._seconds_at[level] = seconds if average is None else average + self.smoothing * (seconds - average)
        self.fixed_cost, self.full_cost = self._fit()

    def _fit(self) -> tuple[float, float]:
        """``(a, c)`` of ``t(level) = a + c / level²`` by least squares over the levels' averages, both ``>= 0``."""
        u = [1.0 / level**2 for level in self._seconds_at]
        t = list(self._seconds_at.values())
        n = len(t)
        if n == 1:
            return 0.0, t[0] / u[0]
        mean_u, mean_t = sum(u) / n, sum(t) / n
        var_u = sum((x - mean_u) ** 2 for x in u)
        c = sum((x - mean_u) * (y - mean_t) for x, y in zip(u, t, strict=True)) / var_u
        a = mean_t - c * mean_u
        if a < 0.0:  # through the origin
            return 0.0, sum(x * y for x, y in zip(u, t, strict=True)) / sum(x * x for x in u)
        if c < 0.0:  # no cost per pixel to be seen
            return mean_t, 0.0
        return a, c

    @property
    def moving_level(self) -> int:
        """The downscale of the latest moving frame (``moving`` until the measured cost moves it)."""
        return self._moving_level

    def _adapt(self) -> int:
        """The moving level for the next frame: kept while its prediction is within the band about the budget,
        else the finest that fits (when none does, the finest within ``overrun`` of the coarsest's time)."""
        predicted = self.predicted_seconds(self._moving_level)
        budget = self.frame_budget
        if predicted is not None and not (1.0 - self.slack) * budget <= predicted <= (1.0 + self.overrun) * budget:
            levels = range(self.still, self.max_downscale + 1)
            fits = [level for level in levels if self.predicted_seconds(level) <= budget]
            if fits:
                self._moving_level = fits[0]
            else:  # the finest level that is not much slower than the coarsest
                floor = self.predicted_seconds(self.max_downscale) * (1.0 + self.overrun)
                self._moving_level = next(level for level in levels if self.predicted_seconds(level) <= floor)
        return self._moving_level

    def next(self, q: torch.Tensor, camera) -> int | None:
        """The downscale to render at now, or ``None`` when the shown image is already the refined one.

        Args:
            q: ``[nT, 3]`` the body's state.
            camera: any comparable description of the view (changes when the camera moves).
        """
        moved = (
            self._q is None
            or self._q.shape != q.shape
            or camera != self._camera
            or float((q - self._q).abs().max()) > self.tolerance
        )
        if moved:
            self._q, self._camera, self._level = q.detach().clone(), camera, self._adapt()
            return self._level
        if self._level != self.still:
            self._level = self.still
            return self.still
        return None
