"""Particles that fill a density field: augmented Poisson-disk sampling (PIE-NeRF §4.1) or a regular grid.

Augmented Poisson-disk sampling sizes each particle by the density gradient (Eq. 3)

    r = max(r̄, κ r̄ / sqrt(‖∇σ‖ + α)),

drops particles whose density is below ε, and gives each the volume of its ball (Eq. 4),
``V = 4/3 π r³``. As written, ``r`` never falls below ``r̄``: ``r = r̄`` wherever
``‖∇σ‖ ≥ κ² − α`` (the density's boundary layer, where σ changes sharply), and ``r`` grows where
σ is flat, up to ``κ r̄ / sqrt(α)`` (≈ 3.2 r̄ for the defaults κ = 0.1, α = 10⁻³) deep inside or
outside a solid. So particles are densest on the boundary and sparser inside, which is the effect
the paper describes ("more particles are needed at the boundary of the shape"). ``κ`` is in the
units of ``sqrt(‖∇σ‖)``; with σ in 1/m, ``κ² − α`` is the gradient (1/m²) below which particles grow.

The volumes of Eq. 4 are those of the balls, not of the Voronoi cells: neighbouring balls overlap
(particles lie at least ``r`` apart, not ``2r``), and a maximal Poisson-disk set covers a solid with
its balls about three times over (random close packing of balls of radius ``r/2`` fills ≈ 38 % of
space, and ``(4/3 π r³) / (4/3 π (r/2)³) = 8``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kernels import backend
from kernels.poisson_disk import poisson_disk_select
from pienerf.sim.density import DensityField

__all__ = ["Particles", "grid_sample", "particle_volume", "poisson_disk_sample", "sample_radius"]

DEFAULT_KAPPA = 0.1
DEFAULT_ALPHA = 1e-3
DEFAULT_EPSILON = 1e-2
DEFAULT_MAX_CANDIDATES = 1 << 24
# Candidate spacing of the jittered grid, as a fraction of r̄.
CANDIDATE_SPACING = 0.5
# Candidates per density evaluation, so that large fields are evaluated in bounded memory.
_EVALUATION_CHUNK = 1 << 18


@dataclass(frozen=True)
class Particles:
    """Particles that sample a solid.

    Attributes:
        position: float32 ``[P, 3]``, metres.
        radius: float32 ``[P]``, metres: no other particle lies closer than this (Eq. 3).
        volume: float32 ``[P]``, cubic metres (Eq. 4 for Poisson-disk particles, the cell for a grid).
        density: float32 ``[P]``, σ at ``position``, per metre.
    """

    position: torch.Tensor
    radius: torch.Tensor
    volume: torch.Tensor
    density: torch.Tensor

    def __post_init__(self):
        n = self.position.shape[0]
        if self.position.shape != (n, 3):
            raise ValueError(f"position must be [P, 3], got {tuple(self.position.shape)}")
        for name in ("position", "radius", "volume", "density"):
            value = getattr(self, name)
            if value.dtype != torch.float32 or value.device != self.position.device:
                raise ValueError(
                    f"{name} must be float32 on {self.position.device}, got {value.dtype} on {value.device}"
                )
            if name != "position" and value.shape != (n,):
                raise ValueError(f"{name} must be [P] with P={n}, got {tuple(value.shape)}")

    def __len__(self) -> int:
        return self.position.shape[0]


def sample_radius(grad_norm: torch.Tensor, r_bar: float, kappa: float, alpha: float = DEFAULT_ALPHA) -> torch.Tensor:
    """Adaptive sample radius ``r = max(r̄, κ r̄ / sqrt(‖∇σ‖ + α))`` (PIE-NeRF Eq. 3).

    Args:
        grad_norm: ``[N]`` density gradient norm ``‖∇σ‖``, per square metre.
        r_bar: ``r̄``, the smallest radius, metres.
        kappa: ``κ``, in the units of ``sqrt(‖∇σ‖)``; ``r = r̄`` where ``‖∇σ‖ ≥ κ² − α``.
        alpha: ``α``, keeps the division finite where the gradient vanishes (paper: 10⁻³).

    Returns:
        ``[N]`` radius ``r``, metres, between ``r̄`` and ``κ r̄ / sqrt(α)``.
    """
    return torch.clamp_min(kappa * r_bar / torch.sqrt(grad_norm + alpha), r_bar)


def particle_volume(radius: torch.Tensor) -> torch.Tensor:
    """Volume assigned to a Poisson-disk particle, the ball ``V = 4/3 π r³`` (PIE-NeRF Eq. 4).

    Args:
        radius: ``[N]`` sample radius ``r`` (Eq. 3), metres.

    Returns:
        ``[N]`` volume, cubic metres.
    """
    return (4.0 / 3.0 * math.pi) * radius**3


def poisson_disk_sample(
    field: DensityField,
    r_bar: float,
    kappa: float = DEFAULT_KAPPA,
    alpha: float = DEFAULT_ALPHA,
    epsilon: float = DEFAULT_EPSILON,
    seed: int = 0,
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
) -> Particles:
    """Augmented Poisson-disk sampling of a density field (PIE-NeRF §4.1, Eq. 3–4).

    Candidates are one uniformly jittered point per cell of a grid of spacing ``r̄ / 2`` over
    ``field.bounds``; those with ``σ < ε`` are dropped, the rest get their radius from Eq. 3 and a
    random priority, and :func:`kernels.poisson_disk.poisson_disk_select` keeps the greedy
    Poisson-disk subset in priority order (in parallel rounds). Two particles conflict when
    ``‖x_i − x_j‖ < max(r_i, r_j)``, so every particle's nearest neighbour is at least its own radius
    away, and no dropped candidate could be added (the set is maximal among the candidates).

    Args:
        field: the density σ(x) and its gradient.
        r_bar: ``r̄``, the smallest particle radius, metres.
        kappa: ``κ`` of Eq. 3 (see :func:`sample_radius`); 0.1 makes interior particles ≈ 3.2 r̄.
        alpha: ``α`` of Eq. 3 (paper: 10⁻³).
        epsilon: ``ε``, candidates with ``σ < ε`` are discarded (paper: 10⁻²).
        seed: seeds the jitter and the priorities; the same seed gives the same particles on a
            given device.
        max_candidates: refuse to build more jittered candidates than this (memory guard).

    Returns:
        :class:`Particles` on the backend device, volumes from Eq. 4.

    Raises:
        ValueError: bad ``r_bar``/``kappa``/``alpha``/``epsilon``, too many candidates, or no
            candidate reaches ``σ ≥ ε``.
    """
    if not (r_bar > 0.0 and math.isfinite(r_bar)):
        raise ValueError(f"r_bar must be a positive radius in metres, got {r_bar}")
    if not (kappa >= 0.0 and math.isfinite(kappa)):
        raise ValueError(f"kappa must be a finite number >= 0 (0 gives radius r_bar everywhere), got {kappa}")
    if not alpha > 0.0:
        raise ValueError(f"alpha must be positive (it keeps Eq. 3 finite where the gradient vanishes), got {alpha}")
    if not epsilon > 0.0:
        raise ValueError(f"epsilon must be a positive density threshold, got {epsilon}")
    device = backend.torch_device()
    generator = torch.Generator().manual_seed(seed)
    lo, hi = (b.to(torch.float64).cpu() for b in field.bounds)
    spacing = CANDIDATE_SPACING * r_bar
    cells = torch.ceil((hi - lo) / spacing).clamp_min(1).long()
    total = int(cells.prod())
    if total > max_candidates:
        raise ValueError(
            f"r_bar={r_bar} m over bounds {(hi - lo).tolist()} m needs {total} candidates, more than "
            f"max_candidates={max_candidates}; raise r_bar or max_candidates"
        )

    kept_position, kept_density = [], []
    for start in range(0, total, _EVALUATION_CHUNK):
        cell = _unravel(torch.arange(start, min(start + _EVALUATION_CHUNK, total)), cells)
        jitter = torch.rand(cell.shape, generator=generator, dtype=torch.float64)
        position = (lo + (cell + jitter) * spacing).to(device=device, dtype=torch.float32)
        sigma = field.density(position)
        keep = sigma >= epsilon
        kept_position.append(position[keep])
        kept_density.append(sigma[keep])
    position = torch.cat(kept_position)
    sigma = torch.cat(kept_density)
    if position.shape[0] == 0:
        raise ValueError(
            f"no particle above the density threshold epsilon={epsilon} among {total} candidates; lower epsilon "
            "or check the density field and its bounds"
        )

    grad_norm = torch.linalg.vector_norm(field.density_grad(position), dim=-1)
    radius = sample_radius(grad_norm, r_bar, kappa, alpha).to(torch.float32)
    priority = torch.randperm(position.shape[0], generator=generator).to(device=device, dtype=torch.int32)
    accepted = poisson_disk_select(position, radius, priority)
    radius = radius[accepted]
    return Particles(
        position=position[accepted],
        radius=radius,
        volume=particle_volume(radius),
        density=sigma[accepted].to(torch.float32),
    )


def grid_sample(
    field: DensityField,
    spacing: float,
    epsilon: float = DEFAULT_EPSILON,
    device: torch.device | str | None = None,
) -> Particles:
    """Particles at the centres of a regular grid's cells where ``σ ≥ ε`` (PIE-NeRF §4.1, Fig. 3 right).

    Args:
        field: the density σ(x).
        spacing: cell edge, metres; each particle gets volume ``spacing³`` and radius ``spacing``
            (its distance to the nearest neighbour, the meaning ``r`` has in Eq. 3).
        epsilon: ``ε``, cells whose centre has ``σ < ε`` are dropped.
        device: where the particles live (default: the backend's device once initialised, else CPU).

    Returns:
        :class:`Particles`.
    """
    if not (spacing > 0.0 and math.isfinite(spacing)):
        raise ValueError(f"spacing must be a positive length in metres, got {spacing}")
    if device is None:
        device = backend.torch_device() if backend.current_device() is not None else torch.device("cpu")
    lo, hi = (b.to(torch.float64).cpu() for b in field.bounds)
    cells = torch.ceil((hi - lo) / spacing).clamp_min(1).long()
    # Centre the grid on the bounds so symmetric shapes are sampled symmetrically.
    origin = 0.5 * (lo + hi) - 0.5 * cells * spacing
    total = int(cells.prod())
    kept_position, kept_density = [], []
    for start in range(0, total, _EVALUATION_CHUNK):
        cell = _unravel(torch.arange(start, min(start + _EVALUATION_CHUNK, total)), cells)
        position = (origin + (cell + 0.5) * spacing).to(device=device, dtype=torch.float32)
        sigma = field.density(position)
        keep = sigma >= epsilon
        kept_position.append(position[keep])
        kept_density.append(sigma[keep])
    position = torch.cat(kept_position)
    if position.shape[0] == 0:
        raise ValueError(
            f"no grid cell above the density threshold epsilon={epsilon}; lower epsilon or spacing, or check "
            "the density field and its bounds"
        )
    n = position.shape[0]
    return Particles(
        position=position,
        radius=torch.full((n,), spacing, dtype=torch.float32, device=device),
        volume=torch.full((n,), spacing**3, dtype=torch.float32, device=device),
        density=torch.cat(kept_density).to(torch.float32),
    )


def _unravel(flat: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Cell indices ``[N, 3]`` (float64) of flat indices into a ``cells[0] × cells[1] × cells[2]`` grid."""
    k = flat % cells[2]
    j = (flat // cells[2]) % cells[1]
    i = flat // (cells[1] * cells[2])
    return torch.stack([i, j, k], dim=-1).to(torch.float64)
