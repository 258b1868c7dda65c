"""The discretised elastic body: particles → Q-GMLS kernels → integrator points → precomputed
shape functions, quadrature and mass (PIE-NeRF §4.2–4.4). Built once; the solver only reads it."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from kernels.ip_integrate import IPIntegrator
from pienerf.sim.integrator_points import (
    IntegratorPoints,
    KernelSet,
    cuboid_quadrature,
    mass_matrix,
    place_integrator_points,
    place_kernels,
)
from pienerf.sim.materials import Material
from pienerf.sim.qgmls import ORDERS, QGMLSBasis, ShapeValues, support_radii
from pienerf.sim.settings import setting

__all__ = ["DiscretizationConfig", "PointHandle", "QGMLSModel"]


@dataclass(frozen=True)
class DiscretizationConfig:
    """How a body is discretised.

    Attributes:
        kernel_count: number of Q-GMLS kernels n (30 DOF each).
        ip_count: number of integrator points K (kernel IPs included); ``None`` → 4n. The paper asks
            for "the same order" as the kernels; with 2n a slender beam of 8–32 kernels came out 1.9–4.5x
            too soft (under-integrated soft modes), with 4n within 6 % of Euler–Bernoulli.
        order: ``"quadratic"`` (Q-GMLS), ``"linear"`` (first-order GMLS) or ``"affine"`` (classical MLS);
            the last two for comparison (locking, Fig. 8).
        quadrature_points_per_axis: Gauss points per cuboid axis g (g³ per IP; module
            :func:`pienerf.sim.integrator_points.cuboid_quadrature` gives the exactness).
        mass_quadrature: ``"cuboid"`` (full rank) or ``"ip"`` (Eq. 11 as written, one point per IP).
        kernel_lloyd_iterations: Lloyd steps of the kernel centres.
        ip_lloyd_iterations: Lloyd steps of the added IPs.
        support_neighbours: k of the support-radius rule (:func:`pienerf.sim.qgmls.support_radii`).
        support_scale: scale of the support-radius rule.
        cuboid_neighbours: particles per IP covariance (§4.4).
        user_kernels: rest positions (m) of kernels the user places (Fig. 5, right).
        cuts: :class:`pienerf.sim.cut.CutPlane` or :class:`pienerf.sim.cut.CutMask` objects; kernels do not
            influence points across a cut, so the pieces separate (Fig. 7).
        quadrature_gradients: ``"exact"``: the exact ∇N at each cuboid quadrature point; ``"taylor"``:
            the paper's first-order expansion about the IP, F(h) = F + ∇F·h (Eq. 14), exact only where
            the field is quadratic, which the rational Q-GMLS shape functions are not. Both are
            precomputed, so a step costs the same; on a cantilever beam with 4 IPs per kernel, exact
            gave +1/+3/+6 % against Euler–Bernoulli for 8/16/32 kernels and Taylor +18/+20/+41 %.
    """

    kernel_count: int = setting(32, low=1, high=100_000, doc="simulation kernels")
    ip_count: int | None = None
    order: str = setting("quadratic", choices=ORDERS, doc="order of the GMLS shape functions")
    quadrature_points_per_axis: int = 2
    mass_quadrature: str = "cuboid"
    kernel_lloyd_iterations: int = setting(5, low=0, high=1000, doc="Lloyd steps of the kernels")
    ip_lloyd_iterations: int = setting(5, low=0, high=1000, doc="Lloyd steps of the integrator points")
    support_neighbours: int = 3
    support_scale: float = 1.3
    cuboid_neighbours: int = 16
    user_kernels: tuple[tuple[float, float, float], ...] = field(default_factory=tuple)
    cuts: tuple = field(default_factory=tuple)
    quadrature_gradients: str = "exact"

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
        if self.quadrature_gradients not in ("taylor", "exact"):
            raise ValueError(f"unknown quadrature_gradients {self.quadrature_gradients!r}; valid: taylor, exact")
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
        # Kernels and IPs are placed on the CPU whatever the device, so that a body is discretised alike on every
        # device and from run to run: on a lattice many particles tie for their nearest centre, and the atomic sums of
        # Lloyd's steps on CUDA broke those ties differently from run to run (a cantilever's tip error at 8 kernels
        # moved between 5 and 8 % on an H100). The placement is a one-off of the model's set-up.
        user = torch.tensor(config.user_kernels, dtype=torch.float64).reshape(-1, 3)
        on_cpu = (position.cpu(), volume.cpu())
        kernels = place_kernels(
            *on_cpu, n, user_points=user if len(user) else None,
            lloyd_iterations=config.kernel_lloyd_iterations,
            neighbours=config.support_neighbours, support_scale=config.support_scale,
        )
        ip_count = min(4 * n if config.ip_count is None else config.ip_count, position.shape[0])
        ips = place_integrator_points(
            *on_cpu, kernels.centres, max(ip_count, n),
            lloyd_iterations=config.ip_lloyd_iterations, neighbours=config.cuboid_neighbours,
        )
        self.kernels: KernelSet = _to_device(kernels, position.device)
        self.ips: IntegratorPoints = _to_device(ips, position.device)
        self.quadrature_offset, self.quadrature_weight = cuboid_quadrature(self.ips, config.quadrature_points_per_axis)
        # Supports must cover every point the shape functions are evaluated at: the particles and the
        # cuboid quadrature points, which on thin or slender bodies can stick out past the particles.
        self.mass_points_per_axis = max(config.quadrature_points_per_axis, 2)
        mass_offset, _ = cuboid_quadrature(self.ips, self.mass_points_per_axis)
        covered = [position] + [(self.ips.position.unsqueeze(1) + o).reshape(-1, 3)
                                for o in (self.quadrature_offset, mass_offset)]
        radius = support_radii(
            self.kernels.centres, torch.cat(covered),
            neighbours=config.support_neighbours, scale=config.support_scale,
        )
        self.basis = QGMLSBasis(
            self.kernels.centres, radius, order=config.order,
            visibility=config.visibility if config.cuts else None,
        )
        self._precompute()

    @classmethod
    def from_particles(cls, particles, config: DiscretizationConfig = DiscretizationConfig()) -> QGMLSModel:
        """Build from :class:`pienerf.sim.sampling.Particles` (Poisson-disk or grid samples of a density)."""
        return cls(particles.position, particles.volume, config, device=particles.position.device)

    def _precompute(self) -> None:
        """Shape functions at IPs and particles, quadrature, mass (everything q-independent)."""
        config = self.config
        if config.quadrature_gradients == "taylor":
            self.ip_shape: ShapeValues = self.basis.evaluate(self.ips.position, derivatives=2)
            # D_kgs = ∇N_s(x_k) + ∇²N_s(x_k) h_g: shape gradients at quadrature points under Eq. 14.
            self.shape_grad = self.ip_shape.grad.unsqueeze(1) + torch.einsum(
                "ksbc,kgc->kgsb", self.ip_shape.hess, self.quadrature_offset
            )
        else:
            self.ip_shape, self.shape_grad = self._exact_quadrature_gradients()
        self.mass = mass_matrix(
            self.basis, self.ips, 1.0, quadrature=config.mass_quadrature,
            points_per_axis=self.mass_points_per_axis,
        )  # per unit density; the solver scales it by ρ
        # Shape jet at the IP centres: the deformed IPs' positions, F and ∇F drive the ray warping (Eq. 19-21).
        self.ip_jet_shape: ShapeValues = self.basis.evaluate(self.ips.position, derivatives=2)
        particle_shape = self.basis.evaluate(self.position, derivatives=1)
        self.particles = PointHandle(self.position, particle_shape.index.clamp_min(0), particle_shape.value)
        self.particle_shape_grad = particle_shape.grad

    def _exact_quadrature_gradients(self) -> tuple[ShapeValues, torch.Tensor]:
        """IP shape values on the union of the shape functions active at the IP and its quadrature
        points, and the exact ∇N_s at every quadrature point ``[K, G, S, 3]``."""
        K, G = self.quadrature_weight.shape
        n = self.shape_count
        points = (self.ips.position.unsqueeze(1) + self.quadrature_offset).reshape(-1, 3)
        at_points = self.basis.evaluate(points, derivatives=1)
        at_ips = self.basis.evaluate(self.ips.position, derivatives=0)
        active = torch.zeros(K, n, dtype=torch.bool, device=self.device)
        for shape, rows in ((at_points, torch.arange(K * G, device=self.device) // G),
                            (at_ips, torch.arange(K, device=self.device))):
            valid = shape.index >= 0
            active[rows[:, None].expand_as(shape.index)[valid], shape.index[valid]] = True
        width = int(active.sum(1).max())
        order = torch.sort(active.to(torch.int8), dim=1, descending=True, stable=True).indices[:, :width]
        index = torch.where(torch.gather(active, 1, order), order, torch.full_like(order, -1))
        slot = torch.full((K, n), -1, dtype=torch.int64, device=self.device)
        slot.scatter_(1, order, torch.arange(width, device=self.device).expand(K, width).contiguous())
        slot = torch.where(active, slot, -1)
        grad = torch.zeros(K * G, width, 3, dtype=torch.float64, device=self.device)
        rows = (torch.arange(K * G, device=self.device) // G)[:, None].expand_as(at_points.index)
        valid = at_points.index >= 0
        target = slot[rows[valid], at_points.index[valid]]
        grad[torch.nonzero(valid)[:, 0], target] = at_points.grad[valid]
        value = torch.zeros(K, width, dtype=torch.float64, device=self.device)
        valid = at_ips.index >= 0
        ip_rows = torch.arange(K, device=self.device)[:, None].expand_as(at_ips.index)
        value[ip_rows[valid], slot[ip_rows[valid], at_ips.index[valid]]] = at_ips.value[valid]
        return ShapeValues(index, value), grad.view(K, G, width, 3)

    @property
    def shape_count(self) -> int:
        """nT: the DOFs are ``[nT, 3]``."""
        return self.basis.shape_count

    @property
    def device(self) -> torch.device:
        return self.position.device

    def integrator(self, material: Material, product_dtype: torch.dtype = torch.float64) -> IPIntegrator:
        """The IP integrator of :mod:`kernels.ip_integrate` for ``material``, its Hessian's block products formed in
        ``product_dtype`` (``torch.float64`` or ``torch.float32``; the Hessian is float64 either way)."""
        mu, lam = material.lame
        return IPIntegrator(
            self.ip_shape.index, self.shape_grad, self.quadrature_weight, self.shape_count, mu, lam, material.kind,
            product_dtype=product_dtype,
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

    def ip_state(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Deformed IPs for the renderer: positions x̃_k ``[K, 3]``, F_k ``[K, 3, 3]`` (Eq. 12) and
        ∇F_k ``[K, 3, 3, 3]`` with ``∇F[k, a, b, c] = ∂F_ab/∂x_c`` (Eq. 15), all at rest position x_k."""
        shape = self.ip_jet_shape
        qs = q[shape.index.clamp_min(0)]  # padded entries carry zero shape values and derivatives
        position = self.ips.position + torch.einsum("ks,ksa->ka", shape.value, qs)
        F = torch.eye(3, dtype=q.dtype, device=q.device) + torch.einsum("ksb,ksa->kab", shape.grad, qs)
        grad_F = torch.einsum("ksbc,ksa->kabc", shape.hess, qs)
        return position, F, grad_F

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


def _to_device(placed, device: torch.device):
    """A copy of a placement (:class:`KernelSet`, :class:`IntegratorPoints`) with its tensors on ``device``."""
    return dataclasses.replace(
        placed,
        **{f.name: getattr(placed, f.name).to(device) for f in dataclasses.fields(placed)
           if isinstance(getattr(placed, f.name), torch.Tensor)},
    )
