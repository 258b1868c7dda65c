"""The discretised elastic body: particles → Q-GMLS kernels → integrator points → precomputed
shape functions, quadrature and mass (PIE-NeRF §4.2–4.4). Built once; the solver only reads it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from kernels.ip_integrate import IPIntegrator
from pienerf.integrator_points import (
    IntegratorPoints,
    KernelSet,
    cuboid_quadrature,
    mass_matrix,
    place_integrator_points,
    place_kernels,
)
from pienerf.materials import Material
from pienerf.qgmls import ORDERS, QGMLSBasis, ShapeValues

__all__ = ["DiscretizationConfig", "PointHandle", "QGMLSModel"]


@dataclass(frozen=True)
class DiscretizationConfig:
    """How a body is discretised.

    Attributes:
        kernel_count: number of Q-GMLS kernels n (30 DOF each).
        ip_count: number of integrator points K (kernel IPs included); ``None`` → 2n.
        order: ``"quadratic"`` (Q-GMLS), ``"linear"`` (first-order GMLS) or ``"affine"`` (classical MLS);
            the last two for comparison (locking, Fig. 8).
        quadrature_points_per_axis: Gauss points per cuboid axis g (g³ per IP; module
            :func:`pienerf.integrator_points.cuboid_quadrature` gives the exactness).
        mass_quadrature: ``"cuboid"`` (full rank) or ``"ip"`` (Eq. 11 as written, one point per IP).
        kernel_lloyd_iterations: Lloyd steps of the kernel centres.
        ip_lloyd_iterations: Lloyd steps of the added IPs.
        support_neighbours: k of the support-radius rule (:func:`pienerf.qgmls.support_radii`).
        support_scale: scale of the support-radius rule.
        cuboid_neighbours: particles per IP covariance (§4.4).
        user_kernels: rest positions (m) of kernels the user places (Fig. 5, right).
        cuts: :class:`pienerf.cut.CutPlane` or :class:`pienerf.cut.CutMask` objects; kernels do not
            influence points across a cut, so the pieces separate (Fig. 7).
    """

    kernel_count: int = 32
    ip_count: int | None = None
    order: str = "quadratic"
    quadrature_points_per_axis: int = 2
    mass_quadrature: str = "cuboid"
    kernel_lloyd_iterations: int = 5
    ip_lloyd_iterations: int = 5
    support_neighbours: int = 3
    support_scale: float = 1.3
    cuboid_neighbours: int = 16
    user_kernels: tuple[tuple[float, float, float], ...] = field(default_factory=tuple)
    cuts: tuple = field(default_factory=tuple)

    def __post_init__(self):
        counts = {
            "kernel_count": self.kernel_count, "quadrature_points_per_axis": self.quadrature_points_per_axis,
            "kernel_lloyd_iterations": self.kernel_lloyd_iterations, "ip_lloyd_iterations": self.ip_lloyd_iterations,
            "support_neighbours": self.support_neighbours, "cuboid_neighbours": self.cuboid_neighbours,
        }
        if self.ip_count is not None:
            counts["ip_count"] = self.ip_count
        for name, value in counts.items():
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if "lloyd" in name else 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.ip_count is not None and self.ip_count < self.kernel_count:
            raise ValueError(f"ip_count ({self.ip_count}) must be >= kernel_count ({self.kernel_count}): "
                             "every kernel centre is an integrator point")
        if self.order not in ORDERS:
            raise ValueError(f"unknown order {self.order!r}; valid: {', '.join(ORDERS)}")
        if self.mass_quadrature not in ("cuboid", "ip"):
            raise ValueError(f"unknown mass_quadrature {self.mass_quadrature!r}; valid: cuboid, ip")
        if not (isinstance(self.support_scale, (int, float)) and math.isfinite(self.support_scale)
                and self.support_scale > 1):
            raise ValueError(f"support_scale must be a finite number > 1, got {self.support_scale!r}")
        points = [v for point in self.user_kernels for v in point]
        if any(not math.isfinite(v) for v in points) or any(len(point) != 3 for point in self.user_kernels):
            raise ValueError(f"user_kernels must be finite (x, y, z) points, got {self.user_kernels!r}")

    def visibility(self, x: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """``[M, n]`` kernels visible from each point through every cut (all True without cuts)."""
        visible = torch.ones(x.shape[0], centres.shape[0], dtype=torch.bool, device=x.device)
        for cut in self.cuts:
            visible &= cut.visibility(x, centres)
        return visible


@dataclass(frozen=True)
class PointHandle:
    """Shape functions at fixed rest points, so that x(q) = X + Σ_s N_s(X) q_s is cheap (Eq. 9).

    Attributes:
        rest: ``[M, 3]`` rest positions (m).
        index: ``[M, S]`` active shape indices (−1 padded → 0 with zero value).
        value: ``[M, S]`` N_s(X).
    """

    rest: torch.Tensor
    index: torch.Tensor
    value: torch.Tensor

    def positions(self, q: torch.Tensor) -> torch.Tensor:
        """Deformed positions ``[M, 3]`` for q ``[nT, 3]``."""
        return self.rest + torch.einsum("ms,msa->ma", self.value, q[self.index])


class QGMLSModel:
    """A body discretised by Q-GMLS, with everything the solver precomputes (§4.2–4.4).

    Args:
        position: particle rest positions ``[P, 3]`` (m), e.g. from Poisson-disk sampling (Eq. 3).
        volume: particle volumes ``[P]`` (m³) (Eq. 4).
        config: discretisation settings.
        device: torch device of every tensor (float64 throughout).
    """

    def __init__(
        self,
        position: torch.Tensor,
        volume: torch.Tensor,
        config: DiscretizationConfig = DiscretizationConfig(),
        device: torch.device | str = "cpu",
    ):
        position = torch.as_tensor(position, dtype=torch.float64, device=device)
        volume = torch.as_tensor(volume, dtype=torch.float64, device=device)
        if position.dim() != 2 or position.shape[1] != 3 or volume.shape != position.shape[:1]:
            raise ValueError(f"particles must be position [P, 3] and volume [P], got {tuple(position.shape)} "
                             f"and {tuple(volume.shape)}")
        if position.shape[0] == 0:
            raise ValueError("the body has no particles; sample the density field with a lower threshold")
        if not (torch.isfinite(position).all() and torch.isfinite(volume).all() and (volume > 0).all()):
            raise ValueError("particle positions must be finite and volumes finite and > 0")
        n = config.kernel_count
        if n > position.shape[0]:
            raise ValueError(
                f"kernel_count {n} exceeds the particle count {position.shape[0]}; lower kernel_count or "
                "sample more particles"
            )
        self.config = config
        self.position = position
        self.volume = volume
        user = torch.tensor(config.user_kernels, dtype=torch.float64, device=device).reshape(-1, 3)
        self.kernels: KernelSet = place_kernels(
            position, volume, n, user_points=user if len(user) else None,
            lloyd_iterations=config.kernel_lloyd_iterations,
            neighbours=config.support_neighbours, support_scale=config.support_scale,
        )
        self.basis = QGMLSBasis(
            self.kernels.centres, self.kernels.support_radius, order=config.order,
            visibility=config.visibility if config.cuts else None,
        )
        ip_count = min(config.ip_count or 2 * n, position.shape[0])
        self.ips: IntegratorPoints = place_integrator_points(
            position, volume, self.kernels.centres, max(ip_count, n),
            lloyd_iterations=config.ip_lloyd_iterations, neighbours=config.cuboid_neighbours,
        )
        self._precompute()

    @classmethod
    def from_particles(cls, particles, config: DiscretizationConfig = DiscretizationConfig()) -> QGMLSModel:
        """Build from :class:`pienerf.sampling.Particles` (Poisson-disk or grid samples of a density)."""
        return cls(particles.position, particles.volume, config, device=particles.position.device)

    def _precompute(self) -> None:
        """Shape functions at IPs and particles, quadrature, mass (everything q-independent)."""
        config = self.config
        self.ip_shape: ShapeValues = self.basis.evaluate(self.ips.position, derivatives=2)
        self.quadrature_offset, self.quadrature_weight = cuboid_quadrature(self.ips, config.quadrature_points_per_axis)
        # D_kgs = ∇N_s(x_k) + ∇²N_s(x_k) h_g: shape gradients at quadrature points under Eq. 14.
        self.shape_grad = self.ip_shape.grad.unsqueeze(1) + torch.einsum(
            "ksbc,kgc->kgsb", self.ip_shape.hess, self.quadrature_offset
        )
        self.mass = mass_matrix(
            self.basis, self.ips, 1.0, quadrature=config.mass_quadrature,
            points_per_axis=max(config.quadrature_points_per_axis, 2),
        )  # per unit density; the solver scales it by ρ
        particle_shape = self.basis.evaluate(self.position, derivatives=1)
        self.particles = PointHandle(self.position, particle_shape.index.clamp_min(0), particle_shape.value)
        self.particle_shape_grad = particle_shape.grad

    @property
    def shape_count(self) -> int:
        """nT: the DOFs are ``[nT, 3]``."""
        return self.basis.shape_count

    @property
    def device(self) -> torch.device:
        return self.position.device

    def integrator(self, material: Material) -> IPIntegrator:
        """The IP integrator of :mod:`kernels.ip_integrate` for ``material``."""
        mu, lam = material.lame
        return IPIntegrator(
            self.ip_shape.index, self.shape_grad, self.quadrature_weight, self.shape_count, mu, lam, material.kind
        )

    def handle(self, rest_points: torch.Tensor) -> PointHandle:
        """Precompute shape functions at rest points (pins, drags, forces, contact proxies)."""
        rest_points = torch.as_tensor(rest_points, dtype=torch.float64, device=self.device).reshape(-1, 3)
        shape = self.basis.evaluate(rest_points, derivatives=0)
        return PointHandle(rest_points, shape.index.clamp_min(0), shape.value)

    def translation(self, t: torch.Tensor) -> torch.Tensor:
        """q ``[nT, 3]`` of a rigid translation ``t [3]``: value DOFs t, derivative DOFs 0 (J q = t)."""
        q = torch.zeros(self.shape_count, 3, dtype=torch.float64, device=self.device)
        q.view(self.basis.kernel_count, self.basis.terms, 3)[:, 0] = torch.as_tensor(t, dtype=torch.float64)
        return q

    def particle_deformation_gradient(self, q: torch.Tensor) -> torch.Tensor:
        """F ``[P, 3, 3]`` at every particle (Eq. 12)."""
        grad_u = torch.einsum("psb,psa->pab", self.particle_shape_grad, q[self.particles.index])
        return grad_u + torch.eye(3, dtype=q.dtype, device=q.device)

    def deformed_volume(self, q: torch.Tensor) -> torch.Tensor:
        """Volume of the deformed body Σ_p V_p det F_p (m³), measured at the particles."""
        return (self.volume * torch.linalg.det(self.particle_deformation_gradient(q))).sum()

    def summary(self) -> dict:
        """Sizes of the discretisation."""
        return {
            "particles": self.position.shape[0],
            "kernels": self.basis.kernel_count,
            "dofs": 3 * self.shape_count,
            "integrator_points": self.ips.count,
            "quadrature_points_per_ip": self.quadrature_weight.shape[1],
            "shape_functions_per_ip": self.ip_shape.index.shape[1],
            "volume_m3": float(self.volume.sum()),
            "bounding_box_m": [round(float(v), 4) for v in (self.position.amax(0) - self.position.amin(0))],
        }
