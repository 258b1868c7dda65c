"""Q-GMLS kernel placement, integrator points, their cuboids and the mass matrix (PIE-NeRF §4.2–4.4, Eq. 10–13).

The object arrives as particles (rest position ``[P, 3]``, volume ``[P]``, e.g. Poisson-disk samples
with ``V = 4/3 π r³``, Eq. 4). From them this module builds, once:

1. the Q-GMLS kernels: farthest-point seeds refined by Lloyd relaxation over the particles' Voronoi
   partition (§4.2), with user-placed kernels kept fixed (Fig. 5, right);
2. the integrator points (IPs, §4.3): one at every kernel centre (kernel IPs) plus farthest-point IPs,
   Lloyd-relaxed with the kernel IPs fixed; each IP carries the volume of its Voronoi cell;
3. a cuboid per IP (§4.4) from the covariance of its nearest particles, and a Gauss–Legendre rule on it;
4. the mass matrix (Eq. 11).

IPs are ordered kernel IPs first (in kernel order), then the added ones. Everything is float64 torch
on the particles' device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pienerf.sim.qgmls import (
    EXACT_CDIST,
    QGMLSBasis,
    ShapeValues,
    as_points,
    support_radii,
    voronoi_partition,
)

__all__ = [
    "IntegratorPoints",
    "KernelSet",
    "cuboid_quadrature",
    "farthest_point_sampling",
    "lloyd_relaxation",
    "mass_matrix",
    "place_integrator_points",
    "place_kernels",
]

_CHUNK = 2048


@dataclass(frozen=True)
class KernelSet:
    """Q-GMLS kernels placed over the particles.

    Attributes:
        centres: ``[n, 3]`` kernel centres ``x_i`` at rest (length); user-placed kernels come first.
        support_radius: ``[n]`` support radii ``ρ_i`` (length), from :func:`pienerf.sim.qgmls.support_radii`.
        cell: ``[P]`` int64 index of the kernel whose Voronoi cell holds each particle.
    """

    centres: torch.Tensor
    support_radius: torch.Tensor
    cell: torch.Tensor


@dataclass(frozen=True)
class IntegratorPoints:
    """Integrator points and their cuboids (§4.3–4.4).

    Attributes:
        position: ``[K, 3]`` IP rest positions ``x_k`` (length).
        volume: ``[K]`` IP volumes ``V_k`` (length³): the particle volume of each IP's Voronoi cell.
        frame: ``[K, 3, 3]`` cuboid axes ``c_1, c_2, c_3`` as orthonormal, right-handed columns.
        extent: ``[K, 3]`` cuboid edge lengths ``h_1 ≥ h_2 ≥ h_3`` (length), ``h_1 h_2 h_3 = V_k`` (Eq. 13).
        is_kernel_ip: ``[K]`` bool, true for the IPs at kernel centres (the first ``n``).
        centre: ``[K, 3]`` cuboid centres (length): the volume centroid of the particles the cuboid was
            fitted to. An IP sits on a particle, which on a plate two particles thick is on one face,
            not the mid-plane; a cuboid centred there would integrate bending about the wrong axis
            (1.75x too stiff for that plate), so the cuboid is centred on the centroid instead and the
            quadrature points are offsets from the IP to it (the Taylor expansion of Eq. 14 stays
            about the IP). ``None`` means the IP positions.
    """

    position: torch.Tensor
    volume: torch.Tensor
    frame: torch.Tensor
    extent: torch.Tensor
    is_kernel_ip: torch.Tensor
    centre: torch.Tensor | None = None

    @property
    def count(self) -> int:
        """Number of IPs ``K``."""
        return self.position.shape[0]


def farthest_point_sampling(points: torch.Tensor, count: int, seed_indices: torch.Tensor | None = None) -> torch.Tensor:
    """Greedy farthest-point sampling: each pick is the point farthest from all picks so far (§4.3).

    ``O(count · P)`` time, ``O(P)`` memory.

    Args:
        points: ``[P, 3]`` positions.
        count: number of points to pick.
        seed_indices: ``[S]`` indices of points already chosen; picks keep away from them and are
            distinct from them. ``None`` starts from the point farthest from the centroid.

    Returns:
        ``[count]`` int64 indices of the picked points (seeds not included), in pick order.
    """
    points = as_points(points, "points")
    seeds = None
    if seed_indices is not None:
        seed_indices = torch.as_tensor(seed_indices, dtype=torch.int64, device=points.device).reshape(-1)
        if seed_indices.numel() and not bool(((seed_indices >= 0) & (seed_indices < points.shape[0])).all()):
            raise ValueError(f"seed_indices must lie in [0, {points.shape[0]})")
        seeds = points[seed_indices]
    free = points.shape[0] - (0 if seed_indices is None else int(torch.unique(seed_indices).numel()))
    _check_count(count, free, "farthest_point_sampling", "points left to pick from")
    return _farthest_from(points, count, seeds)


def lloyd_relaxation(
    points: torch.Tensor,
    weights: torch.Tensor,
    centres: torch.Tensor,
    iterations: int,
    fixed_mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lloyd relaxation of centres over a weighted point set.

    Each iteration partitions the points by nearest centre (Voronoi cells) and moves every free
    centre to the weighted centroid of its cell, *snapped to the cell's point nearest to that
    centroid*. Snapping keeps centres inside the object (a cell of a curved or thin object can have
    its centroid in empty space) and keeps them distinct (cells are disjoint). Centres whose cell is
    empty, and fixed centres, stay where they are. Stops early once no centre moves.

    Args:
        points: ``[P, 3]`` positions (the particles).
        weights: ``[P]`` non-negative weights (the particle volumes).
        centres: ``[n, 3]`` initial centres.
        iterations: number of relaxation steps (≥ 0).
        fixed_mask: ``[n]`` bool, true for centres that must not move; ``None`` frees all.

    Returns:
        ``(centres [n, 3], cell [P])``: relaxed centres and the Voronoi cell of each point under them.
    """
    points, centres = as_points(points, "points"), as_points(centres, "centres").to(points.device)
    weights = _as_weights(weights, points.shape[0], "weights")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    n = centres.shape[0]
    free = torch.ones(n, dtype=torch.bool, device=points.device)
    if fixed_mask is not None:
        fixed_mask = torch.as_tensor(fixed_mask, dtype=torch.bool, device=points.device)
        if fixed_mask.shape != (n,):
            raise ValueError(f"fixed_mask must be [n] = [{n}] like centres, got {tuple(fixed_mask.shape)}")
        free = ~fixed_mask
    cell, _ = voronoi_partition(points, centres)
    for _ in range(iterations):
        mass = torch.zeros(n, dtype=torch.float64, device=points.device).index_add_(0, cell, weights)
        moment = torch.zeros_like(centres).index_add_(0, cell, weights.unsqueeze(-1) * points)
        centroid = torch.where(mass.unsqueeze(-1) > 0, moment / mass.clamp_min(1e-300).unsqueeze(-1), centres)
        snapped = _snap_to_cell(points, cell, centroid, centres)
        moved = torch.where(free.unsqueeze(-1), snapped, centres)
        if torch.equal(moved, centres):
            break
        centres = moved
        cell, _ = voronoi_partition(points, centres)
    return centres, cell


def place_kernels(
    position: torch.Tensor,
    volume: torch.Tensor,
    count: int,
    user_points: torch.Tensor | None = None,
    lloyd_iterations: int = 5,
    neighbours: int = 4,
    support_scale: float = 1.5,
) -> KernelSet:
    """Place ``count`` Q-GMLS kernels over the particles (§4.2).

    User-placed kernels (if any) are kept fixed; the others start at farthest-point samples of the
    particles (away from the user kernels) and are Lloyd-relaxed with the particle volumes as
    weights, so each kernel centre ends on a particle near the volume centroid of its Voronoi cell.

    Args:
        position: ``[P, 3]`` particle rest positions (length).
        volume: ``[P]`` particle volumes (length³).
        count: total number of kernels ``n``, user-placed ones included.
        user_points: ``[U, 3]`` user-placed kernel centres, or ``None``.
        lloyd_iterations: Lloyd steps for the free kernels.
        neighbours: ``k`` of the support-radius rule (:func:`pienerf.sim.qgmls.support_radii`).
        support_scale: ``scale`` of the support-radius rule.

    Returns:
        :class:`KernelSet`.
    """
    position = as_points(position, "position")
    volume = _as_weights(volume, position.shape[0], "volume")
    user = torch.zeros(0, 3, dtype=torch.float64, device=position.device)
    if user_points is not None:
        user = as_points(user_points, "user_points").to(position.device)
    if isinstance(count, bool) or not isinstance(count, int) or count < max(1, user.shape[0]):
        raise ValueError(f"count must be an int >= max(1, number of user kernels = {user.shape[0]}), got {count!r}")
    _check_count(count - user.shape[0], position.shape[0], "place_kernels", "particles")
    free = _farthest_from(position, count - user.shape[0], user if user.shape[0] else None)
    centres = torch.cat([user, position[free]])
    fixed = torch.arange(count, device=position.device) < user.shape[0]
    centres, cell = lloyd_relaxation(position, volume, centres, lloyd_iterations, fixed_mask=fixed)
    radius = support_radii(centres, position, neighbours=neighbours, scale=support_scale)
    return KernelSet(centres=centres, support_radius=radius, cell=cell)


def place_integrator_points(
    position: torch.Tensor,
    volume: torch.Tensor,
    kernel_centres: torch.Tensor,
    count: int,
    lloyd_iterations: int = 5,
    neighbours: int = 16,
    cuboid_from: str = "cell",
) -> IntegratorPoints:
    """Integrator points with their volumes and cuboids (§4.3–4.4).

    Kernel IPs sit at the kernel centres; ``count − n`` more start at the particles farthest from
    all IPs so far and are Lloyd-relaxed with the kernel IPs fixed (farthest-point picks crowd the
    boundary; relaxation spreads them into the interior). Each IP's volume ``V_k`` is the particle
    volume of its Voronoi cell, so the volumes sum to the particles' total (the paper's ``Σ_j V_j``
    over each IP's ``K`` nearest particles would count shared neighbours several times).

    Cuboid (§4.4): over a set of particles around the IP — its own Voronoi cell
    (``cuboid_from="cell"``, the default) or, as the paper words it, the ``K = neighbours`` particles
    nearest to it (``cuboid_from="neighbours"``) — the volume-weighted covariance about their mean,
    ``C = Σ_j V_j [(x_j − x̄)(x_j − x̄)ᵀ + (s_j²/12) I] / Σ_j V_j`` with ``s_j = V_j^{1/3}``. Its
    eigenvectors are the cuboid axes and ``h_i ∝ √(12 λ_i)`` (the edges of a uniform box with that
    covariance), scaled so that ``h_1 h_2 h_3 = V_k``. The ``s_j²/12`` term is the second moment of a
    cube of the particle's own volume: it floors the eigenvalues so that a layer one particle thick
    (a thin plate, where the paper's covariance is singular) gets a cuboid one particle thick
    instead of a zero edge, which the volume constraint could not satisfy. In thick regions it is
    negligible next to the spread of the particles.

    Why the cell by default: the cuboid must have the IP's volume. Fitting the K-neighbour ratios to
    that volume scales all three edges alike, so wherever the cell is smaller than the neighbourhood
    a thin plate's cuboid comes out thinner or thicker than the plate (1.2x thicker was measured on a
    two-particle-thick plate, which stiffens bending by about its square). The cell's own covariance
    has extents √(12 λ_i) whose product already approximates the cell volume, so the volume fit
    barely rescales them and a layer keeps its true thickness.

    Args:
        position: ``[P, 3]`` particle rest positions (length).
        volume: ``[P]`` particle volumes (length³).
        kernel_centres: ``[n, 3]`` kernel centres (length).
        count: total number of IPs ``K`` ≥ ``n``, kernel IPs included.
        lloyd_iterations: Lloyd steps for the added IPs.
        neighbours: particles per covariance for ``cuboid_from="neighbours"`` (clamped to ``P``).
        cuboid_from: ``"cell"`` or ``"neighbours"`` (above).

    Returns:
        :class:`IntegratorPoints` with the kernel IPs first.
    """
    position = as_points(position, "position")
    volume = _as_weights(volume, position.shape[0], "volume")
    kernel_centres = as_points(kernel_centres, "kernel_centres").to(position.device)
    n = kernel_centres.shape[0]
    if isinstance(count, bool) or not isinstance(count, int) or count < n:
        raise ValueError(
            f"count is the total number of integrator points and must be an int >= the number of kernels "
            f"({n}), got {count!r}"
        )
    if neighbours < 1:
        raise ValueError(f"neighbours must be >= 1, got {neighbours}")
    if cuboid_from not in ("cell", "neighbours"):
        raise ValueError(f"cuboid_from must be 'cell' or 'neighbours', got {cuboid_from!r}")
    _check_count(count - n, position.shape[0], "place_integrator_points", "particles")
    added = _farthest_from(position, count - n, kernel_centres if n else None)
    ips = torch.cat([kernel_centres, position[added]])
    is_kernel_ip = torch.arange(count, device=position.device) < n
    ips, cell = lloyd_relaxation(position, volume, ips, lloyd_iterations, fixed_mask=is_kernel_ip)
    ip_volume = torch.zeros(count, dtype=torch.float64, device=position.device).index_add_(0, cell, volume)
    if cuboid_from == "cell":
        centre, frame, extent = _cell_cuboids(position, volume, cell, ip_volume)
    else:
        centre, frame, extent = _cuboids(position, volume, ips, ip_volume, min(neighbours, position.shape[0]))
    return IntegratorPoints(
        position=ips, volume=ip_volume, frame=frame, extent=extent, is_kernel_ip=is_kernel_ip, centre=centre
    )


def cuboid_quadrature(ips: IntegratorPoints, points_per_axis: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Tensor-product Gauss–Legendre rule on each IP cuboid ``[−h/2, h/2]³`` (Eq. 13).

    With ``g`` points per axis the rule integrates polynomials of degree ``2g − 1`` in each local
    coordinate exactly. Under Eq. 14, ``F(h)`` is linear in ``h``, so an energy density that is a
    polynomial of degree ``d`` in ``F`` (StVK: ``d = 4``) is integrated exactly once ``2g − 1 ≥ d``:
    ``g = 3`` for StVK, ``g = 2`` for a quadratic (linear-elastic) density; ``g = 1`` is Eq. 11's
    single point per IP.

    Args:
        ips: the integrator points.
        points_per_axis: ``g`` ≥ 1.

    Returns:
        ``(offset [K, g³, 3], weight [K, g³])``: world-frame offsets ``h`` of the quadrature points from
        each IP (length; the cuboid is centred on ``ips.centre``) and quadrature weights (length³) that
        sum to each IP's volume.
    """
    if isinstance(points_per_axis, bool) or not isinstance(points_per_axis, int) or points_per_axis < 1:
        raise ValueError(f"points_per_axis must be an int >= 1 (2 or 3 are typical), got {points_per_axis!r}")
    nodes, weights = np.polynomial.legendre.leggauss(points_per_axis)
    device = ips.position.device
    nodes = torch.as_tensor(nodes, dtype=torch.float64, device=device)
    weights = torch.as_tensor(weights, dtype=torch.float64, device=device) / 2.0
    grid = torch.cartesian_prod(nodes, nodes, nodes).reshape(-1, 3)  # [g³, 3] in [-1, 1]³
    grid_weight = torch.cartesian_prod(weights, weights, weights).reshape(-1, 3).prod(-1)  # sums to 1
    local = 0.5 * grid.unsqueeze(0) * ips.extent.unsqueeze(1)  # [K, g³, 3] in the cuboid frame
    offset = torch.einsum("kab,kgb->kga", ips.frame, local)
    if ips.centre is not None:
        offset = offset + (ips.centre - ips.position).unsqueeze(1)
    return offset, ips.volume.unsqueeze(-1) * grid_weight


def mass_matrix(
    basis: QGMLSBasis,
    ips: IntegratorPoints,
    density: float,
    quadrature: str = "ip",
    points_per_axis: int = 3,
) -> torch.Tensor:
    """Mass matrix ``M = Σ_k ρ V_k J(x_k)ᵀ J(x_k)`` (Eq. 11), as its scalar factor.

    With ``J = N ⊗ I3`` (Eq. 9), ``M = M_N ⊗ I3`` for the flat DOF index ``s * 3 + a``; this returns
    ``M_N [nT, nT]`` with ``(M_N)_st = ρ Σ_k V_k N_s(x_k) N_t(x_k)``. The full ``[3nT, 3nT]`` matrix is
    ``torch.kron(M_N, torch.eye(3))``.

    ``quadrature="ip"`` is Eq. 11 as written: one point per IP. Its rank is at most ``K`` (a sum of
    ``K`` rank-one terms), below ``nT = 10 n`` when the IP count is of the order of the kernel count,
    so it is singular. ``quadrature="cuboid"`` integrates ``ρ N Nᵀ`` over every IP cuboid with the
    Gauss–Legendre rule of :func:`cuboid_quadrature` (``points_per_axis³`` points each), evaluating
    ``N`` exactly at those points: a better approximation of ``∫ ρ JᵀJ dΩ`` that is full rank once
    ``K · points_per_axis³ ≥ nT`` (and the points are in general position).

    Args:
        basis: the Q-GMLS shape functions.
        ips: the integrator points.
        density: mass density ``ρ`` (mass / length³), ``> 0``.
        quadrature: ``"ip"`` or ``"cuboid"``.
        points_per_axis: Gauss points per cuboid axis for ``"cuboid"``.

    Returns:
        ``[nT, nT]`` symmetric positive semi-definite float64 matrix (mass).
    """
    if not density > 0:
        raise ValueError(f"density must be > 0 (mass per unit volume), got {density}")
    if quadrature == "ip":
        points, weight = ips.position, ips.volume
    elif quadrature == "cuboid":
        offset, weight = cuboid_quadrature(ips, points_per_axis)
        points, weight = (ips.position.unsqueeze(1) + offset).reshape(-1, 3), weight.reshape(-1)
    else:
        raise ValueError(f"unknown quadrature {quadrature!r}; valid: 'ip', 'cuboid'")
    shape = basis.evaluate(points.to(basis.centres.device), derivatives=0)
    weight = density * weight.to(basis.centres.device)
    mass = torch.zeros(basis.shape_count, basis.shape_count, dtype=torch.float64, device=basis.centres.device)
    for rows in torch.arange(points.shape[0], device=mass.device).split(_CHUNK):
        chunk = ShapeValues(shape.index[rows], shape.value[rows]).dense_value(basis.shape_count)
        mass += chunk.T @ (weight[rows].unsqueeze(-1) * chunk)
    return 0.5 * (mass + mass.T)


def _farthest_from(points: torch.Tensor, count: int, seeds: torch.Tensor | None) -> torch.Tensor:
    """``count`` farthest-point picks among ``points``, starting away from ``seeds [S, 3]`` (or none)."""
    picks = torch.empty(count, dtype=torch.int64, device=points.device)
    if count == 0:
        return picks
    if seeds is None:  # no seeds: start from the point farthest from the centroid
        picks[0] = torch.argmax(((points - points.mean(0)) ** 2).sum(-1))
        distance, start = ((points - points[picks[0]]) ** 2).sum(-1), 1
    else:
        distance, start = voronoi_partition(points, seeds)[1] ** 2, 0
    for i in range(start, count):
        picks[i] = torch.argmax(distance)
        distance = torch.minimum(distance, ((points - points[picks[i]]) ** 2).sum(-1))
    return picks


def _snap_to_cell(
    points: torch.Tensor, cell: torch.Tensor, target: torch.Tensor, fallback: torch.Tensor
) -> torch.Tensor:
    """For each cell, the member point nearest to ``target[cell]``; ``fallback`` for empty cells."""
    distance = ((points - target[cell]) ** 2).sum(-1)
    by_distance = torch.argsort(distance, stable=True)
    order = by_distance[torch.argsort(cell[by_distance], stable=True)]
    sorted_cell = cell[order]
    first = torch.ones_like(sorted_cell, dtype=torch.bool)
    first[1:] = sorted_cell[1:] != sorted_cell[:-1]
    snapped = fallback.clone()
    snapped[sorted_cell[first]] = points[order[first]]
    return snapped


def _cuboids(
    position: torch.Tensor, volume: torch.Tensor, centres: torch.Tensor, target_volume: torch.Tensor, neighbours: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cuboid centres ``[K, 3]``, frames ``[K, 3, 3]`` and edges ``[K, 3]`` from neighbour covariances (§4.4)."""
    centres_out, frames, extents = [], [], []
    eye = torch.eye(3, dtype=torch.float64, device=position.device)
    for rows in torch.arange(centres.shape[0], device=position.device).split(_CHUNK):
        distances = torch.cdist(centres[rows], position, compute_mode=EXACT_CDIST)
        nearest = distances.topk(neighbours, dim=1, largest=False).indices
        x, v = position[nearest], volume[nearest]  # [C, K, 3], [C, K]
        total = v.sum(1, keepdim=True).clamp_min(1e-300)
        mean = (v.unsqueeze(-1) * x).sum(1, keepdim=True) / total.unsqueeze(-1)
        spread = x - mean
        cube = (v ** (2.0 / 3.0) / 12.0).unsqueeze(-1).unsqueeze(-1) * eye  # second moment of a cube of volume v
        moment = spread.unsqueeze(-1) * spread.unsqueeze(-2) + cube
        covariance = torch.einsum("ck,ckab->cab", v, moment) / total.unsqueeze(-1)
        eigenvalues, eigenvectors = torch.linalg.eigh(covariance)  # ascending
        eigenvalues, eigenvectors = eigenvalues.flip(-1), eigenvectors.flip(-1)
        eigenvalues = eigenvalues.clamp_min(1e-12 * eigenvalues[:, :1].clamp_min(1e-300))
        handed = torch.linalg.det(eigenvectors).sign()
        eigenvectors = torch.cat([eigenvectors[..., :2], eigenvectors[..., 2:] * handed[:, None, None]], -1)
        ratio = eigenvalues.sqrt()
        scale = (target_volume[rows] / ratio.prod(-1)) ** (1.0 / 3.0)
        centres_out.append(mean.squeeze(1))
        frames.append(eigenvectors)
        extents.append(ratio * scale.unsqueeze(-1))
    return torch.cat(centres_out), torch.cat(frames), torch.cat(extents)


def _cell_cuboids(
    position: torch.Tensor, volume: torch.Tensor, cell: torch.Tensor, target_volume: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cuboid centres ``[K, 3]``, frames ``[K, 3, 3]`` and edges ``[K, 3]`` from each IP's Voronoi cell."""
    count = target_volume.shape[0]
    eye = torch.eye(3, dtype=torch.float64, device=position.device)
    mass = torch.zeros(count, dtype=torch.float64, device=position.device).index_add_(0, cell, volume)
    first = torch.zeros(count, 3, dtype=torch.float64, device=position.device)
    first.index_add_(0, cell, volume[:, None] * position)
    second = torch.zeros(count, 3, 3, dtype=torch.float64, device=position.device)
    own = position[:, :, None] * position[:, None, :] + (volume ** (2.0 / 3.0) / 12.0)[:, None, None] * eye
    second.index_add_(0, cell, volume[:, None, None] * own)
    mean = first / mass.clamp_min(1e-300)[:, None]
    covariance = second / mass.clamp_min(1e-300)[:, None, None] - mean[:, :, None] * mean[:, None, :]
    return (mean, *_frame_and_extent(covariance, target_volume))


def _frame_and_extent(covariance: torch.Tensor, target_volume: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Principal axes (right-handed, longest first) and edges √(12 λ_i) scaled to ``target_volume``."""
    eigenvalues, eigenvectors = torch.linalg.eigh(0.5 * (covariance + covariance.mT))  # ascending
    eigenvalues, eigenvectors = eigenvalues.flip(-1), eigenvectors.flip(-1)
    eigenvalues = eigenvalues.clamp_min(1e-12 * eigenvalues[:, :1].clamp_min(1e-300))
    handed = torch.linalg.det(eigenvectors).sign()
    eigenvectors = torch.cat([eigenvectors[..., :2], eigenvectors[..., 2:] * handed[:, None, None]], -1)
    natural = (12.0 * eigenvalues).sqrt()
    scale = (target_volume / natural.prod(-1)) ** (1.0 / 3.0)
    return eigenvectors, natural * scale.unsqueeze(-1)


def _check_count(count: int, available: int, what: str, noun: str) -> None:
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"{what}: count must be a non-negative int, got {count!r}")
    if count > available:
        raise ValueError(
            f"{what}: asked for {count} new points but there are only {available} {noun}; "
            "ask for fewer or sample the object more densely"
        )


def _as_weights(weights: torch.Tensor, count: int, name: str) -> torch.Tensor:
    weights = torch.as_tensor(weights)
    if weights.shape != (count,):
        raise ValueError(f"{name} must be [P] = [{count}] like the positions, got {tuple(weights.shape)}")
    if not bool((torch.isfinite(weights) & (weights >= 0)).all()) or not float(weights.sum()) > 0:
        raise ValueError(f"{name} must be finite, non-negative and not all zero")
    return weights.to(torch.float64)
