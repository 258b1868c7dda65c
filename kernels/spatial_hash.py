"""Neighbour queries on a point set through Warp's hash grid: fixed-radius neighbours and k nearest.

A :class:`SpatialHash` buckets the points once (``wp.HashGrid``: cubic cells of edge ``cell_size``,
hashed into a fixed table, so unbounded scenes cost no more memory than bounded ones); every query
then visits only the cells that overlap its search ball. Build once, query many times: the renderer
asks millions of ray samples for their neighbours among a few hundred particles every frame.

Warp rather than Taichi: ``wp.HashGrid`` is a tested, sorted-bucket grid that builds on both devices,
and on CUDA Warp's hash-grid kernel is the faster of the two (``docs/benchmarks.md``). On the CPU Warp runs a
kernel on one thread.

Distances are Euclidean, in the units of the points (metres in this project), compared in float32.
"""

# Warp needs int(0)/bool(True) to declare variables that change inside dynamic loops.
# ruff: noqa: UP018

import math

import torch
import warp as wp

from kernels import backend

__all__ = ["SpatialHash", "knn", "knn3_exhaustive_row", "knn_row", "radius_neighbours"]

# Hashed cells per axis; the table has at most this cubed entries whatever the extent of the scene.
_MAX_GRID_DIM = 128


@wp.kernel
def _radius_query(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    queries: wp.array(dtype=wp.vec3),
    radius: float,
    index: wp.array2d(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    q = wp.tid()
    x = queries[q]
    capacity = index.shape[1]
    radius_sq = radius * radius
    found = int(0)
    j = int(0)
    query = wp.hash_grid_query(grid, x, radius)
    while wp.hash_grid_query_next(query, j):
        if wp.length_sq(points[j] - x) <= radius_sq:
            if found < capacity:
                index[q, found] = j
            found += 1
    count[q] = found


@wp.func
def _before(distance_sq_a: float, index_a: int, distance_sq_b: float, index_b: int) -> bool:
    # Nearest first; equal distances in increasing point index, so ties have one answer.
    return distance_sq_a < distance_sq_b or (distance_sq_a == distance_sq_b and index_a < index_b)


@wp.func
def knn_row(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    x: wp.vec3,
    start_radius: float,
    max_radius: float,
    index: wp.array2d(dtype=wp.int32),
    distance: wp.array2d(dtype=wp.float32),
    row: int,
):
    """The ``k = index.shape[1]`` nearest points of ``x`` into row ``row`` of ``index``/``distance`` (a Warp function,
    for kernels that search as part of their work; :meth:`SpatialHash.knn` describes the search and the result).

    The row holds the current k best as an insertion-sorted list of squared distances while the search ball doubles
    from ``start_radius`` until it holds k points (then the k nearest lie inside it) or reaches ``max_radius``.
    (Keeping the best three in registers instead, for k = 3, was measured no faster on an H100: the cells' visits
    dominate.)
    """
    k = index.shape[1]
    radius = start_radius
    kept = int(0)
    searching = bool(True)
    while searching:
        radius_sq = radius * radius
        found = int(0)
        kept = int(0)
        j = int(0)
        query = wp.hash_grid_query(grid, x, radius)
        while wp.hash_grid_query_next(query, j):
            d_sq = wp.length_sq(points[j] - x)
            if d_sq <= radius_sq:
                found += 1
                slot = int(-1)
                if kept < k:
                    slot = kept
                    kept += 1
                elif _before(d_sq, j, distance[row, k - 1], index[row, k - 1]):
                    slot = k - 1
                if slot >= 0:
                    while slot > 0 and _before(d_sq, j, distance[row, slot - 1], index[row, slot - 1]):
                        distance[row, slot] = distance[row, slot - 1]
                        index[row, slot] = index[row, slot - 1]
                        slot -= 1
                    distance[row, slot] = d_sq
                    index[row, slot] = j
        if found >= k or radius >= max_radius:
            searching = False
        else:
            radius = wp.min(2.0 * radius, max_radius)
    for s in range(k):
        if s < kept:
            distance[row, s] = wp.sqrt(distance[row, s])
        else:
            distance[row, s] = wp.inf
            index[row, s] = -1


@wp.func
def knn3_exhaustive_row(
    points: wp.array(dtype=wp.vec3),
    x: wp.vec3,
    max_radius: float,
    index: wp.array2d(dtype=wp.int32),
    distance: wp.array2d(dtype=wp.float32),
    row: int,
):
    """:func:`knn_row`'s row for k = 3 by looking at every point (no grid): the same row, faster for a few hundred
    points, where visiting the grid's cells costs more than measuring every distance (all threads read the same
    point at once, so the points stream from cache)."""
    max_sq = max_radius * max_radius
    d0 = float(wp.inf)
    d1 = float(wp.inf)
    d2 = float(wp.inf)
    i0 = int(-1)
    i1 = int(-1)
    i2 = int(-1)
    for j in range(points.shape[0]):
        d_sq = wp.length_sq(points[j] - x)
        if d_sq <= max_sq:
            d0, i0, d1, i1, d2, i2 = _insert3(d_sq, j, d0, i0, d1, i1, d2, i2)
    _write3(d0, i0, d1, i1, d2, i2, index, distance, row)


@wp.func
def _insert3(d_sq: float, j: int, d0: float, i0: int, d1: float, i1: int, d2: float, i2: int):
    """The three best (squared distance, index) pairs, sorted by :func:`_before`, with (d_sq, j) offered."""
    if _before(d_sq, j, d2, i2):
        if _before(d_sq, j, d1, i1):
            if _before(d_sq, j, d0, i0):
                return d_sq, j, d0, i0, d1, i1
            return d0, i0, d_sq, j, d1, i1
        return d0, i0, d1, i1, d_sq, j
    return d0, i0, d1, i1, d2, i2


@wp.func
def _write3(
    d0: float, i0: int, d1: float, i1: int, d2: float, i2: int,
    index: wp.array2d(dtype=wp.int32), distance: wp.array2d(dtype=wp.float32), row: int,
):
    """Row ``row`` from the three best squared distances (empty places: (inf, −1), as :func:`knn_row` leaves them)."""
    index[row, 0] = i0
    index[row, 1] = i1
    index[row, 2] = i2
    distance[row, 0] = wp.sqrt(d0)
    distance[row, 1] = wp.sqrt(d1)
    distance[row, 2] = wp.sqrt(d2)


@wp.kernel
def _knn_query(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    queries: wp.array(dtype=wp.vec3),
    start_radius: float,
    max_radius: float,
    index: wp.array2d(dtype=wp.int32),
    distance: wp.array2d(dtype=wp.float32),
):
    q = wp.tid()
    knn_row(grid, points, queries[q], start_radius, max_radius, index, distance, q)


class SpatialHash:
    """A hash grid over a fixed point set, built once and queried many times.

    Args:
        points: float32 ``[P, 3]`` on the backend device, ``P >= 1``; kept by reference (the grid
            indexes into it), so do not modify it while this object lives.
        cell_size: edge of the cubic cells, metres. Queries are fastest when their radius is close
            to it (a query visits ``ceil(2 * radius / cell_size + 1)^3`` cells at most).

    Raises:
        ValueError: the point set is empty or malformed, or ``cell_size`` is not positive.
    """

    def __init__(self, points: torch.Tensor, cell_size: float):
        _check_points(points, "points")
        if points.shape[0] == 0:
            raise ValueError("SpatialHash needs at least one point; the point set is empty (check the sampling step)")
        if not (cell_size > 0.0 and math.isfinite(cell_size)):
            raise ValueError(f"cell_size must be a positive finite length in metres, got {cell_size}")
        self.points = points
        self.cell_size = float(cell_size)
        self._points_wp = backend.to_warp(points, dtype=wp.vec3)
        dim = int(min(_MAX_GRID_DIM, max(8, 2 * math.ceil(points.shape[0] ** (1.0 / 3.0)))))
        self.grid = wp.HashGrid(dim, dim, dim, device=backend.warp_device())
        self.grid.build(self._points_wp, self.cell_size)
        lo, hi = points.amin(0), points.amax(0)
        # Mean volume per point of the bounding box (padded by one cell so flat sets are not zero).
        self._volume_per_point = float(torch.prod(hi - lo + self.cell_size)) / points.shape[0]

    @property
    def points_warp(self):
        """The points as a ``wp.array`` of ``vec3`` (for kernels that search through :func:`knn_row`)."""
        return self._points_wp

    @property
    def grid_id(self) -> int:
        """The ``wp.HashGrid`` id to pass to other Warp kernels querying the same points."""
        return self.grid.id

    def radius_neighbours(
        self, queries: torch.Tensor, radius: float, max_neighbours: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """All points within ``radius`` (inclusive) of each query.

        Args:
            queries: float32 ``[Q, 3]`` on the backend device.
            radius: search radius, metres, ``> 0``.
            max_neighbours: columns of the returned index table, ``>= 1``.

        Returns:
            ``(index, count)``: ``index`` int32 ``[Q, max_neighbours]``, point indices padded with -1,
            in no particular order; ``count`` int32 ``[Q]``, the true number of points within
            ``radius``. When ``count > max_neighbours`` the row holds the first ``max_neighbours``
            the traversal met (an arbitrary subset), so compare ``count`` with ``max_neighbours``
            to detect truncation.
        """
        _check_points(queries, "queries")
        if not (radius > 0.0 and math.isfinite(radius)):
            raise ValueError(f"radius must be a positive finite length in metres, got {radius}")
        if max_neighbours < 1:
            raise ValueError(f"max_neighbours must be at least 1, got {max_neighbours}")
        index = torch.full((queries.shape[0], max_neighbours), -1, dtype=torch.int32, device=queries.device)
        count = torch.zeros(queries.shape[0], dtype=torch.int32, device=queries.device)
        if queries.shape[0] > 0:
            wp.launch(
                _radius_query,
                dim=queries.shape[0],
                inputs=[
                    self.grid.id,
                    self._points_wp,
                    backend.to_warp(queries, dtype=wp.vec3),
                    float(radius),
                    backend.to_warp(index),
                    backend.to_warp(count),
                ],
                device=backend.warp_device(),
            )
        return index, count

    def start_radius(self, k: int, max_radius: float) -> float:
        """Radius of the ball expected to hold ``k`` points at the set's mean density (within ``max_radius``): where a
        k-nearest search (:meth:`knn`, :func:`knn_row`) starts."""
        start = (3.0 * k * self._volume_per_point / (4.0 * math.pi)) ** (1.0 / 3.0)
        return min(max(start, 1e-3 * self.cell_size), max_radius)

    def knn(self, queries: torch.Tensor, k: int, max_radius: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``k`` nearest points of each query, nearest first, searched within ``max_radius``.

        The search starts from the radius of a ball expected to hold ``k`` points at the set's mean
        density and doubles it until it holds ``k`` points or reaches ``max_radius``, so a query
        far from every point costs ``log2(max_radius / start)`` passes.

        Args:
            queries: float32 ``[Q, 3]`` on the backend device.
            k: neighbours per query, ``>= 1`` (may exceed the number of points).
            max_radius: largest distance searched, metres, ``> 0``.

        Returns:
            ``(index, distance)``: int32 ``[Q, k]`` point indices and float32 ``[Q, k]`` distances
            (metres), sorted by distance and, among equal distances, by index. Slots beyond the
            points found within ``max_radius`` hold -1 and ``inf``.
        """
        _check_points(queries, "queries")
        _check_knn_arguments(k, max_radius)
        start = self.start_radius(k, max_radius)
        index = torch.empty((queries.shape[0], k), dtype=torch.int32, device=queries.device)
        distance = torch.empty((queries.shape[0], k), dtype=torch.float32, device=queries.device)
        if queries.shape[0] > 0:
            wp.launch(
                _knn_query,
                dim=queries.shape[0],
                inputs=[
                    self.grid.id,
                    self._points_wp,
                    backend.to_warp(queries, dtype=wp.vec3),
                    float(start),
                    float(max_radius),
                    backend.to_warp(index),
                    backend.to_warp(distance),
                ],
                device=backend.warp_device(),
            )
        return index, distance


def radius_neighbours(
    points: torch.Tensor, queries: torch.Tensor, radius: float, max_neighbours: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """All of ``points`` within ``radius`` of each query; one-shot form of :meth:`SpatialHash.radius_neighbours`.

    Args:
        points: float32 ``[P, 3]`` on the backend device, ``P >= 1``.
        queries: float32 ``[Q, 3]`` on the backend device.
        radius: search radius, metres (also the cell size of the grid built for this call).
        max_neighbours: columns of the returned index table.

    Returns:
        ``(index [Q, max_neighbours] int32 padded with -1, count [Q] int32)`` as in
        :meth:`SpatialHash.radius_neighbours`.
    """
    return SpatialHash(points, radius).radius_neighbours(queries, radius, max_neighbours)


def knn(points: torch.Tensor, queries: torch.Tensor, k: int, max_radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest of ``points`` to each query; one-shot form of :meth:`SpatialHash.knn`.

    The grid's cell size is the largest extent of ``points`` times ``(k / P)^(1/3)`` (capped at
    ``max_radius``): about the edge of a cube holding ``k`` points at their mean density.

    Args:
        points: float32 ``[P, 3]`` on the backend device, ``P >= 1``.
        queries: float32 ``[Q, 3]`` on the backend device.
        k: neighbours per query.
        max_radius: largest distance searched, metres.

    Returns:
        ``(index [Q, k] int32, distance [Q, k] float32)``, -1 and ``inf`` where fewer than ``k``
        points lie within ``max_radius``.
    """
    _check_points(points, "points")
    if points.shape[0] == 0:
        raise ValueError("knn needs at least one point; the point set is empty (check the sampling step)")
    _check_knn_arguments(k, max_radius)
    largest_extent = float((points.amax(0) - points.amin(0)).max())
    cell = largest_extent * (k / points.shape[0]) ** (1.0 / 3.0) if largest_extent > 0.0 else max_radius
    return SpatialHash(points, min(cell, max_radius)).knn(queries, k, max_radius)


def _check_points(tensor: torch.Tensor, what: str) -> None:
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.dtype != torch.float32:
        raise TypeError(f"{what} must be float32, got {tensor.dtype}; convert with .float()")
    if tensor.dim() != 2 or tensor.shape[1] != 3:
        raise ValueError(f"{what} must have shape [N, 3], got {tuple(tensor.shape)}")


def _check_knn_arguments(k: int, max_radius: float) -> None:
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    if not (max_radius > 0.0 and math.isfinite(max_radius)):
        raise ValueError(f"max_radius must be a positive finite length in metres, got {max_radius}")
