"""The incremental potential of an implicit Q-GMLS step and its Newton system (PIE-NeRF Eq. 2, 9, 18).

One implicit Euler step with q_{n+1} = q_n + h q̇_{n+1} minimises

    E(q) = 1/(2h²) ‖q − q̂‖²_M + U(q) − fᵀq + 1/(2h) (q − q_n)ᵀ D (q − q_n) + E_s(q) + E_c(q),   q̂ = q_n + h q̇_n

with the mass matrix M (Eq. 11), the elastic energy U integrated at the integrator points
(:class:`kernels.ip_integrate.IPIntegrator`), the external and gravity forces f (f_q = Jᵀ(X) f, Eq. 9; gravity
M q_g), Rayleigh damping D = αM + βK(q_n), the springs E_s of pins and drags (zero rest length, from material points
to targets) and the collider penalty E_c. :class:`QGMLSPotential` evaluates each term, its gradient and Hessian, and
the Newton system of Eq. 18. Both Newton loops (:mod:`pienerf.sim.solver.host_loop`,
:mod:`pienerf.sim.solver.device_loop`) are built from its public methods.

Coordinates q are ``[nT, 3]`` float64 (Eq. 9 layout, nT shape functions); Hessians are ``[3nT, 3nT]`` with the
three coordinates of a shape function adjacent. Lengths are metres, energies joules, forces newtons.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from kernels.ip_integrate import DENSE_ASSEMBLY_RATIO, IPIntegral, IPIntegrator
from pienerf.sim.materials import Material
from pienerf.sim.model import PointHandle, QGMLSModel
from pienerf.sim.solver.config import SolverConfig
from pienerf.sim.solver.state import PlaneCollider, PointTargets, QGMLSControl, SphereCollider

__all__ = [
    "LINE_SEARCH_FAILURES",
    "QGMLSPotential",
    "StepContext",
    "collider_distance",
    "collider_placement",
]

LINE_SEARCH_FAILURES = ("inversion", "no decrease", "not finite")
"""The kinds of a failed line search (:attr:`pienerf.sim.solver.QGMLSStepReport.line_search_failure`)."""


class StepContext(NamedTuple):
    """What one step holds fixed: its start, inertial target, external force and time step.

    Attributes:
        q_n: ``[nT, 3]`` coordinates at the start of the step.
        q_hat: ``[nT, 3]`` inertial target q_n + h q̇_n.
        f_ext: ``[nT, 3]`` generalized external force, gravity included (N).
        inv_h: 1/h (1/s).
        inv_h2: 1/h² (1/s²).
    """

    q_n: torch.Tensor
    q_hat: torch.Tensor
    f_ext: torch.Tensor
    inv_h: float
    inv_h2: float


def collider_distance(kind, x: torch.Tensor, a: torch.Tensor, b) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distances ``[P]`` (m) of points ``x [P, 3]`` to a collider and its outward unit normals ``[P, 3]``: for
    :class:`PlaneCollider`, the plane through ``a [3]`` with unit normal ``b [3]``; for :class:`SphereCollider`, the
    sphere of centre ``a [3]`` and radius ``b`` (m)."""
    if kind is PlaneCollider:
        return (x - a) @ b, b.expand_as(x)
    d = x - a
    dist = d.norm(dim=1).clamp_min(1e-12)
    return dist - b, d / dist[:, None]


def collider_placement(collider: PlaneCollider | SphereCollider) -> torch.Tensor:
    """A collider's placement as float64 numbers on the CPU: ``[6]`` point and unit normal of a plane, ``[4]`` centre
    and radius of a sphere (m); :meth:`QGMLSPotential.collider_penalty` reads them."""
    if isinstance(collider, PlaneCollider):
        normal = torch.tensor(collider.normal, dtype=torch.float64)
        return torch.cat([torch.tensor(collider.point, dtype=torch.float64), normal / normal.norm()])
    if isinstance(collider, SphereCollider):
        return torch.tensor([*collider.centre, collider.radius], dtype=torch.float64)
    raise TypeError(f"unknown collider {collider!r}; use PlaneCollider or SphereCollider")


class QGMLSPotential:
    """The terms of the incremental potential of a :class:`QGMLSModel` body of a :class:`Material`.

    Attributes:
        model: the discretised body.
        config: the solver's settings (gravity, damping, contact stiffness, Hessian precision, tolerances).
        material: the material (:meth:`set_material`).
        integrator: the elastic integrator with float64 block products (exact to round-off).
        step_integrator: the one Newton steps use, its products in ``config.hessian_precision``.
        mass: ``[nT, nT]`` scalar mass matrix ρ M (kg, Eq. 11); ``mass_flat`` is M ⊗ I₃ ``[3nT, 3nT]``.
        gravity_force: ``[nT, 3]`` generalized gravity M q_g (N).
        contact_spring: ``[P]`` collider penalty stiffness of each particle (N/m).

    Springs' Hessians k JᵀJ are kept between calls of :meth:`spring_hessian` per handle object: a
    :class:`PointHandle` is frozen and its tensors are never written in place (a handle for other points is a new
    handle, :meth:`QGMLSModel.handle`), so the same handle object has the same JᵀJ.
    """

    def __init__(self, model: QGMLSModel, material: Material, config: SolverConfig):
        self.model = model
        self.config = config
        self.integrator: IPIntegrator | None = None
        self.step_integrator: IPIntegrator | None = None
        self.jtj_products = 0  # JᵀJ products formed for springs (:meth:`spring_hessian`)
        self._eye3 = torch.eye(3, dtype=torch.float64, device=model.device)
        self._n = model.shape_count
        self.set_material(material)

    def _integrator(self, product_dtype: torch.dtype) -> IPIntegrator:
        """The integrator of the material whose Hessian's block products are formed in ``product_dtype``, made once
        per material."""
        integrator = self._integrators.get(product_dtype)
        if integrator is None:
            integrator = self._integrators[product_dtype] = self.model.integrator(self.material, product_dtype)
        return integrator

    def set_material(self, material: Material) -> None:
        """Change the material: the integrators' Lamé parameters, the mass and gravity (density), the contact springs
        (Young's modulus, where ``config.contact_stiffness`` is ``None``)."""
        self.material = material
        model = self.model
        if self.integrator is None or material.kind != self.integrator.model:
            self._integrators: dict[torch.dtype, IPIntegrator] = {}  # by block-product dtype (:meth:`_integrator`)
        for integrator in self._integrators.values():
            integrator.set_material(*material.lame)
        self.integrator = self._integrator(torch.float64)
        self.step_integrator = self._integrator(self.config.hessian_product_dtype(model.device))
        self.mass = material.density * model.mass  # [nT, nT] scalar mass (Eq. 11)
        self.mass_flat = torch.kron(self.mass, self._eye3)
        gravity = model.translation(torch.tensor(self.config.gravity, dtype=torch.float64))
        self.gravity_force = self.mass @ gravity
        stiffness = self.config.contact_stiffness
        if stiffness is None:
            stiffness = 100.0 * material.young_modulus
        self.contact_spring = stiffness * model.volume.pow(1.0 / 3.0)
        self._spring_cache: dict[int, tuple] = {}

    @property
    def shape_count(self) -> int:
        """nT, the number of shape functions (q is ``[nT, 3]``)."""
        return self._n

    # -- measures ------------------------------------------------------------------------------

    def displacement(self, dq: torch.Tensor) -> torch.Tensor:
        """Largest displacement |J(x_k) dq| over the integrator points (m) of an update ``dq [nT, 3]``, as a 0-d tensor
        (no host read): the Newton stopping measure, in metres whatever the DOF (values, gradients and second
        derivatives of the shape functions have different units)."""
        shape = self.model.ip_shape
        return torch.einsum("ks,ksa->ka", shape.value, dq[shape.index.clamp_min(0)]).abs().max()

    def displacement_norm(self, dq: torch.Tensor) -> float:
        """:meth:`displacement` read on the host (m)."""
        return float(self.displacement(dq))

    # -- points: forces, springs, contacts ----------------------------------------------------------

    def add_point_forces(self, grad: torch.Tensor, index: torch.Tensor, value: torch.Tensor, force: torch.Tensor):
        """``grad [nT, 3] += Jᵀ f`` (Eq. 9) for forces ``force [M, 3]`` (N) at points with shape indices
        ``index [M, S]`` and values ``value [M, S]``; in place."""
        grad.index_add_(0, index.reshape(-1), (value[..., None] * force[:, None, :]).reshape(-1, 3))

    def point_shape_matrix(self, index: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        """Shape values ``value [M, S]`` at ``index [M, S]`` scattered into the rows N_s(X_m) ``[M, nT]``."""
        rows = value.new_zeros(value.shape[0], self._n)
        return rows.scatter_add_(1, index, value)

    def isotropic_point_hessian(self, index: torch.Tensor, value: torch.Tensor, stiffness: torch.Tensor):
        """Σ_m k_m J_mᵀ J_m ``[3nT, 3nT]`` for stiffnesses ``[M]`` (N/m): (Nᵀ diag(k) N) ⊗ I₃, one product."""
        rows = self.point_shape_matrix(index, value)
        return torch.kron((rows * stiffness[:, None]).T @ rows, self._eye3)

    def normal_point_hessian(self, index, value, stiffness, normal, by_blocks: bool | None = None) -> torch.Tensor:
        """Σ_m k_m J_mᵀ n_m n_mᵀ J_m ``[3nT, 3nT]`` for stiffnesses ``[M]`` (N/m) and unit normals ``[M, 3]``.

        Points that see most shape functions (S close to nT): Wᵀ W with rows W_m = √k_m (N_m ⊗ n_m), one product.
        Otherwise (many narrow kernels, where that product's (3nT)² work per point would dominate) each point's
        [S, S] blocks are summed into place (:meth:`kernels.ip_integrate.IPIntegrator.assemble_blocks`).
        ``by_blocks``: force one assembly (``None``: by :data:`kernels.ip_integrate.DENSE_ASSEMBLY_RATIO`).
        """
        if by_blocks is None:
            by_blocks = (self._n / max(index.shape[1], 1)) ** 2 >= DENSE_ASSEMBLY_RATIO
        if by_blocks:
            scale = stiffness[:, None, None] * value[:, :, None] * value[:, None, :]
            blocks = scale[..., None] * (normal[:, :, None] * normal[:, None, :]).reshape(-1, 1, 1, 9)
            block_index = (index[:, :, None] * self._n + index[:, None, :]).reshape(-1)
            return self.integrator.assemble_blocks(blocks.reshape(-1, 9), block_index)
        rows = self.point_shape_matrix(index, value)
        weighted = (stiffness.sqrt()[:, None, None] * rows[:, :, None] * normal[:, None, :]).reshape(len(rows), -1)
        return weighted.T @ weighted

    def handle_jtj(self, handle: PointHandle) -> torch.Tensor:
        """Jᵀ J ``[3nT, 3nT]`` of a handle's points (a spring's Hessian at unit stiffness)."""
        self.jtj_products += 1
        return self.isotropic_point_hessian(handle.index, handle.value, torch.ones_like(handle.value[:, 0]))

    def spring_hessian(self, springs: list[PointTargets]) -> torch.Tensor | None:
        """Σ over springs of k Jᵀ J ``[3nT, 3nT]`` (``None`` without springs): constant, the springs being quadratic,
        and independent of the targets. Jᵀ J of each handle is kept while the same handle object comes back, so a pin
        held over many steps costs one product, once; a drag moving its target reuses its own."""
        cache, H = {}, None
        for spring in springs:
            handle = spring.handle
            entry = cache.get(id(handle)) or self._spring_cache.get(id(handle))
            if entry is None or entry[0] is not handle:
                entry = (handle, self.handle_jtj(handle))
            cache[id(handle)] = entry
            part = entry[1] * spring.stiffness
            H = part if H is None else H.add_(part)
        self._spring_cache = cache  # handles no longer used are let go
        return H

    def spring_energy(self, q: torch.Tensor, springs, gradient: bool = True):
        """Energy ½ k Σ|x − target|² (J) and its gradient ``[nT, 3]`` (``None`` without ``gradient``) of springs given
        as ``(handle, target [M, 3], stiffness)``, the stiffness a number or a 0-d tensor (N/m)."""
        energy, grad = q.new_zeros(()), torch.zeros_like(q) if gradient else None
        for handle, target, stiffness in springs:
            r = handle.positions(q) - target
            energy = energy + 0.5 * stiffness * (r * r).sum()
            if gradient:
                self.add_point_forces(grad, handle.index, handle.value, stiffness * r)
        return energy, grad

    def spring_terms(self, springs: list[PointTargets], q: torch.Tensor, hessian: bool, gradient: bool = True):
        """Energy, gradient (``None`` without ``gradient``) and Hessian (``None`` without ``hessian``) of the
        springs at ``q``."""
        energy, grad = self.spring_energy(q, ((s.handle, s.target, s.stiffness) for s in springs), gradient)
        return energy, grad, self.spring_hessian(springs) if hessian else None

    def contact_terms(self, colliders, q: torch.Tensor, hessian: bool):
        """Energy ½ Σ k φ² over the particles inside a collider (φ < 0), its gradient ``[nT, 3]`` and (``hessian``)
        its Gauss–Newton Hessian Σ k Jᵀ n nᵀ J ``[3nT, 3nT]`` (``None`` where no particle is inside).
        Reads the device (which particles are inside): the host loop's."""
        energy = q.new_zeros(())
        grad = torch.zeros_like(q)
        H = None
        if not colliders:
            return energy, grad, H
        particles = self.model.particles
        x = particles.positions(q)
        for collider in colliders:
            if isinstance(collider, PlaneCollider):
                normal = torch.tensor(collider.normal, dtype=q.dtype, device=q.device)
                point = torch.tensor(collider.point, dtype=q.dtype, device=q.device)
                phi, normals = collider_distance(PlaneCollider, x, point, normal / normal.norm())
            elif isinstance(collider, SphereCollider):
                centre = torch.tensor(collider.centre, dtype=q.dtype, device=q.device)
                phi, normals = collider_distance(SphereCollider, x, centre, collider.radius)
            else:
                raise TypeError(f"unknown collider {collider!r}; use PlaneCollider or SphereCollider")
            active = phi < 0
            if not bool(active.any()):
                continue
            k, p, nrm = self.contact_spring[active], phi[active], normals[active]
            index, value = particles.index[active], particles.value[active]
            energy = energy + 0.5 * (k * p * p).sum()
            self.add_point_forces(grad, index, value, (k * p)[:, None] * nrm)  # ∂E/∂x = k φ n
            if hessian:
                # Gauss–Newton block k n nᵀ (exact for planes; drops the sphere's curvature term)
                part = self.normal_point_hessian(index, value, k, nrm)
                H = part if H is None else H + part
        return energy, grad, H

    def collider_penalty(self, kinds, placements, q: torch.Tensor, gradient: bool, hessian: bool):
        """:meth:`contact_terms` over every particle, those outside contributing zero, so that nothing is read on the
        host: colliders given by their ``kinds`` and ``placements`` (:func:`collider_placement`, on the model's
        device). Returns energy (J), gradient ``[nT, 3]`` (``None`` without ``gradient``) and Hessian (``None``
        without ``hessian`` or colliders)."""
        particles = self.model.particles
        energy, grad, H = q.new_zeros(()), torch.zeros_like(q) if gradient else None, None
        if not kinds:
            return energy, grad, H
        x = particles.positions(q)
        k = self.contact_spring
        for kind, values in zip(kinds, placements, strict=True):
            phi, normals = collider_distance(kind, x, values[:3], values[3:] if kind is PlaneCollider else values[3])
            depth = phi.clamp(max=0.0)
            energy = energy + 0.5 * (k * depth * depth).sum()
            if gradient:
                self.add_point_forces(grad, particles.index, particles.value, (k * depth)[:, None] * normals)
            if hessian:
                part = self.normal_point_hessian(particles.index, particles.value, k * (phi < 0), normals)
                H = part if H is None else H + part
        return energy, grad, H

    # -- forces and the step's potential ---------------------------------------------------------

    def external_force(self, forces) -> torch.Tensor:
        """Generalized external force ``[nT, 3]`` (N): gravity M q_g plus Jᵀ f of point forces given as
        ``(handle, force [M, 3])``."""
        f = self.gravity_force.clone()
        for handle, force in forces:
            self.add_point_forces(f, handle.index, handle.value, force)
        return f

    def control_force(self, control: QGMLSControl) -> torch.Tensor:
        """:meth:`external_force` of a control's point forces."""
        return self.external_force((f.handle, f.force) for f in control.forces)

    def step_context(self, q_n: torch.Tensor, qd_n: torch.Tensor, f_ext: torch.Tensor, dt: float) -> StepContext:
        """The :class:`StepContext` of a step of ``dt`` seconds from ``(q_n, qd_n)`` under ``f_ext``."""
        return StepContext(q_n, q_n + dt * qd_n, f_ext, 1.0 / dt, 1.0 / dt**2)

    def incremental_energy(self, x: torch.Tensor, ctx: StepContext, damping_K, elastic) -> torch.Tensor:
        """Inertia, elastic (``elastic``: U(x), J), external-force and damping terms of the incremental potential
        (Eq. 2) at ``x [nT, 3]`` (J, 0-d); ``damping_K``: K(q_n) ``[3nT, 3nT]`` where β > 0, else ``None``."""
        inv_h = ctx.inv_h
        dx_hat, dx = x - ctx.q_hat, x - ctx.q_n
        energy = 0.5 * inv_h**2 * (dx_hat * (self.mass @ dx_hat)).sum() + elastic - (ctx.f_ext * x).sum()
        if self.config.rayleigh_alpha:
            energy = energy + 0.5 * inv_h * self.config.rayleigh_alpha * (dx * (self.mass @ dx)).sum()
        if damping_K is not None:
            energy = energy + 0.5 * inv_h * self.config.rayleigh_beta * (dx.reshape(-1) @ (damping_K @ dx.reshape(-1)))
        return energy

    def newton_system(self, q: torch.Tensor, ctx: StepContext, elastic: IPIntegral, damping_K, gradients, hessians):
        """The incremental potential's gradient ``[nT, 3]`` at ``q`` and, where ``elastic`` carries the elastic
        Hessian, the Newton matrix of Eq. 18 ``[3nT, 3nT]``: M/h² + αM/h + ∂²U/∂q² + βK/h + the ``hessians`` of springs
        and contacts, built in the elastic Hessian's storage (``None`` otherwise). ``gradients``: the springs' and
        contacts' gradients."""
        alpha, beta = self.config.rayleigh_alpha, self.config.rayleigh_beta
        inv_h2, inv_h = ctx.inv_h2, ctx.inv_h
        dx_hat, dx = q - ctx.q_hat, q - ctx.q_n
        grad = inv_h2 * (self.mass @ dx_hat) + elastic.gradient - ctx.f_ext
        for part in gradients:
            grad = grad + part
        if alpha:
            grad = grad + alpha * inv_h * (self.mass @ dx)
        if damping_K is not None:
            grad = grad + beta * inv_h * (damping_K @ dx.reshape(-1)).view_as(q)
        H = elastic.hessian
        if H is not None:
            H.add_(self.mass_flat, alpha=inv_h2 + alpha * inv_h)
            if damping_K is not None:
                H.add_(damping_K, alpha=beta * inv_h)
            for part in hessians:
                if part is not None:
                    H += part
        return grad, H

    def exact_newton_matrix(self, q: torch.Tensor, ctx: StepContext, damping_K, gradients, hessians) -> torch.Tensor:
        """:meth:`newton_system`'s matrix at ``q`` with float64 block products (the one to fall back on where float32
        products make the matrix singular)."""
        elastic = self.integrator.evaluate(q, hessian=True, project=self.config.project_hessian)
        return self.newton_system(q, ctx, elastic, damping_K, gradients, hessians)[1]

    def is_stationary(self, step: torch.Tensor, slope: torch.Tensor, energy: torch.Tensor) -> torch.Tensor:
        """Whether an iterate is stationary to round-off, as a 0-d bool tensor (no host read): the energy and the
        Newton ``step [nT, 3]`` finite, and the step below ``newton_tolerance`` or its predicted decrease −``slope``
        below the energy's rounding. A line search that finds nothing there is no failure."""
        finite = torch.isfinite(step).all() & torch.isfinite(energy)
        small = self.displacement(step) < self.config.newton_tolerance
        flat = -slope <= 64.0 * torch.finfo(torch.float64).eps * energy.abs()
        return finite & (small | flat)

    def line_search_failure(self, step: torch.Tensor, slope, energy, trials: list[torch.Tensor]) -> str:
        """Why no trial along ``step`` was accepted (one of :data:`LINE_SEARCH_FAILURES`); ``""`` when the iterate is
        stationary to round-off (the Newton step is below ``newton_tolerance`` or its predicted decrease −slope below
        the energy's rounding). ``trials``: the rejected trial energies, +inf for an inverted trial."""
        if not bool(torch.isfinite(step).all()) or not math.isfinite(float(energy)):
            return "not finite"
        if self.displacement_norm(step) < self.config.newton_tolerance:
            return ""
        if -float(slope) <= 64.0 * torch.finfo(torch.float64).eps * abs(float(energy)):
            return ""
        values = torch.stack(trials)
        if bool(torch.isnan(values).any()):
            return "not finite"
        if bool(torch.isinf(values).all()):
            return "inversion"
        return "no decrease"
