"""The incremental potential of the garment simulator: inertia, membrane, bending, IPC barrier and lagged friction.

One implicit Euler step minimises ``E(x) = ½‖x − x̂‖²_M + Δt² (Ψ_s(x) + Ψ_b(x) + κ B(x) + D(x))`` over the free
garment vertices (PhysAvatar §3.2, Appendix A.3; :mod:`physavatar.cloth`). :class:`IncrementalPotential` evaluates
``E``, its gradient and its element Hessians (:class:`~physavatar.cloth.newton_system.NewtonElement`) from the
element kernels (:class:`ClothEnergies`: :mod:`kernels.shell`, :mod:`kernels.contact`) and the friction of
:mod:`physavatar.cloth.contact`, and holds the material's parameters: lumped masses, Lamé parameters, hinge
stiffness and the barrier stiffness ``κ``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from kernels import backend, element_terms, ipc_barrier, shell
from kernels import contact as kernels_contact
from physavatar.cloth.config import ClothConfig
from physavatar.cloth.contact import REACH, ContactPairs, LaggedFriction, compact_rows, friction_potential
from physavatar.cloth.newton_system import NewtonElement

__all__ = [
    "ClothEnergies",
    "IncrementalPotential",
    "StepContext",
    "barrier_stiffness",
    "bending_stiffness",
    "lumped_masses",
]

F64 = torch.float64


class ClothEnergies(NamedTuple):
    """Per-element energy evaluators (signatures of :func:`kernels.shell.membrane_energy`, ``bending_energy``,
    ``contact_energy`` and their energy-only ``*_value`` twins, which the line search calls); the benchmark swaps
    in the autograd references."""

    membrane: Callable = shell.membrane_energy
    bending: Callable = shell.bending_energy
    contact: Callable = kernels_contact.contact_energy
    membrane_value: Callable = shell.membrane_energy_value
    bending_value: Callable = shell.bending_energy_value
    contact_value: Callable = kernels_contact.contact_energy_value


class StepContext(NamedTuple):
    """What one step of the simulator holds fixed: its size, ``κ``, start, inertial target, free DOFs, friction."""

    dt: float
    kappa: float
    x_start: torch.Tensor  # [V + B, 3] positions at the start of the step
    x_hat: torch.Tensor  # [V, 3] inertial target
    x_rest: torch.Tensor  # [V + B, 3] rest positions (mollifier thresholds)
    kinematic: torch.Tensor  # [V + B] bool
    dof: torch.Tensor  # [V + B] int32 free index or −1
    free: torch.Tensor  # [n] free vertices
    friction: LaggedFriction | None


def lumped_masses(x: torch.Tensor, faces: torch.Tensor, areal_density: float) -> torch.Tensor:
    """Lumped vertex masses ``m_i = ρ h Σ_{f ∋ i} A_f / 3`` (C-IPC's shell mass).

    Args:
        x: ``[V, 3]`` rest positions, m.
        faces: ``[F, 3]`` vertex indices.
        areal_density: ``ρ h``, kg/m².

    Returns:
        ``[V]`` masses, kg.
    """
    tri = x[faces.long()]
    area = 0.5 * torch.linalg.norm(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    mass = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
    return mass.index_add_(0, faces.long().reshape(-1), (areal_density * area / 3.0).repeat_interleave(3))


def bending_stiffness(config: ClothConfig) -> float:
    """Hinge stiffness ``k = κ_b E₀ h³ / (24 (1 − ν²))``, J (PhysAvatar's κ_b, §3.2).

    ``κ_b`` multiplies the base modulus ``E₀`` directly, independently of the membrane's ``κ_s``, so that
    ``(ρ, κ_s, κ_b)`` enter mass, membrane and bending separately. The hinge energy is ``k w̄ (θ − θ̄)²``
    (:func:`kernels.shell.bending_energy`); on a square grid bent about a grid axis its continuum limit has
    bending rigidity ``6 k`` per unit width (``4.8 k`` for a free strip).
    """
    e, h, nu = config.base_young, config.thickness, config.poisson
    return config.kappa_b * e * h**3 / (24.0 * (1.0 - nu * nu))


def barrier_stiffness(config: ClothConfig, mean_mass: float, dt: float) -> float:
    """IPC barrier stiffness ``κ``, J/m⁴: the configured one, or C-IPC's rule from the mean vertex mass.

    C-IPC sets the barrier's curvature in the distance at a separation of 10⁻⁸ m, ``4·10⁻¹⁶ b″(10⁻¹⁶)``, to
    ``3·10¹¹ m̄`` in the incremental potential; here the barrier enters as ``Δt² κ B``, hence the ``Δt²``.
    """
    if config.barrier_stiffness is not None:
        return config.barrier_stiffness
    dhat2 = config.contact_distance**2
    d = torch.tensor([1e-16], dtype=F64, device=backend.torch_device())
    curvature = float(ipc_barrier.barrier(d, dhat2)[2][0])
    return 3.0e11 * mean_mass / (dt * dt * 4.0e-16 * curvature)


class IncrementalPotential:
    """The incremental potential ``E`` of one garment and the material parameters it is made of.

    Vertices ``0 … V − 1`` are the garment's, ``V … V + B − 1`` the body's, in every position array ``X [V + B, 3]``
    it is given (m, float64); the body enters only through the contact pairs.

    Args:
        x_rest: ``[V, 3]`` float64 garment rest positions on the backend device, m.
        faces: ``[F, 3]`` int32 garment triangles on the backend device, consistently oriented, manifold.
        config: material, contact and friction settings.
        energies: the element evaluators.

    Raises:
        ValueError: a non-manifold or inconsistently oriented garment (from :func:`kernels.shell.hinges_from_faces`).
    """

    def __init__(self, x_rest: torch.Tensor, faces: torch.Tensor, config: ClothConfig, energies: ClothEnergies):
        device = backend.torch_device()
        self.config = config
        self.energies = energies
        self.vertex_count = x_rest.shape[0]
        self.x_rest = x_rest
        self.faces = faces
        self.hinges, _ = shell.hinges_from_faces(self.faces)
        self.rest = shell.rest_state(self.x_rest, self.faces, self.hinges)
        self.mass = lumped_masses(self.x_rest, self.faces, config.density * config.thickness)
        mu, lam = shell.plane_stress_lame(config.young, config.poisson, config.thickness)
        self.membrane_mu, self.membrane_lambda = mu, lam
        self.k_bend = bending_stiffness(config)
        self.gravity = torch.tensor(config.gravity, dtype=F64, device=device)
        self._kappa: dict[float, float] = {}  # barrier stiffness by step size

    def kappa(self, dt: float) -> float:
        """The barrier stiffness ``κ`` of steps of ``dt`` seconds, J/m⁴ (:func:`barrier_stiffness`, once per ``dt``)."""
        if dt not in self._kappa:
            self._kappa[dt] = barrier_stiffness(self.config, float(self.mass.mean()), dt)
        return self._kappa[dt]

    def inertia_diagonal(self, free: torch.Tensor) -> torch.Tensor | None:
        """The masses ``[n]`` (kg) of the ``free`` vertices, the Newton matrix's inertia diagonal; ``None`` in a static
        solve, which has no inertia."""
        return None if self.config.static else self.mass[free]

    def evaluate(
        self,
        X: torch.Tensor,
        candidates: ContactPairs,
        ctx: StepContext,
        project: bool = True,
        parts: dict[str, torch.Tensor] | None = None,
        active: tuple[torch.Tensor, torch.Tensor] | None = None,
    ):
        """Incremental potential ``E(X)``, its gradient ``[V + B, 3]`` and the element Hessians (:meth:`energy` is
        ``E`` alone). ``candidates`` may be any superset of the contact pairs within ``d̂`` of ``X``. ``active``, when
        given, is :meth:`active_rows` of ``X`` and ``candidates`` (a fixed number of rows, padded: the Newton loop on
        CUDA); each contact element's ``reach`` is then its own pairs, not the pairs within ``REACH · d̂``.

        The element Hessians are to be PSD-filtered as they are assembled (:class:`NewtonElement`), unless ``project``
        is False (friction's are PSD by construction).
        ``parts``, when given, receives the gradient ``[V + B, 3]`` of each term that is present, by name:
        ``"inertia"`` (``M (x − x̂)``, or ``−Δt² M g`` in a static solve), and, scaled by ``Δt²``, ``"membrane"``,
        ``"bending"``, ``"contact"`` and ``"friction"``.

        Returns ``(energy, grad, elements)`` with ``elements`` a list of :class:`NewtonElement`.
        """
        cfg, dt2 = self.config, ctx.dt * ctx.dt
        v = self.vertex_count
        x = X[:v].contiguous()
        # every element term is scaled by Δt²: their energies and gradients are summed unscaled, then scaled once
        term_energies: list[torch.Tensor] = []
        term_grad = torch.zeros_like(X)
        elements: list[NewtonElement] = []
        free_mask = ~ctx.kinematic[:v]

        def add(index, terms, name: str, projection: str = "none", reach=None) -> None:
            term_energies.append(terms.energy)
            term_grad.index_add_(0, index.reshape(-1), terms.grad.reshape(-1, 3))
            if index.shape[0] or reach is not None and reach.shape[0]:
                elements.append(NewtonElement(index, terms.hess, dt2, projection, reach, exact_psd=name == "contact"))
            if parts is not None:
                part = parts.setdefault(name, torch.zeros_like(X))
                part.index_add_(0, index.reshape(-1), dt2 * terms.grad.reshape(-1, 3))

        if cfg.static:
            energy = -dt2 * (self.mass[:, None] * self.gravity * x).sum()
            inertia = -dt2 * self.mass[:, None] * self.gravity
        else:
            r = (x - ctx.x_hat) * free_mask[:, None]
            energy = 0.5 * (self.mass[:, None] * r * r).sum()
            inertia = self.mass[:, None] * r
        if parts is not None:
            parts["inertia"] = torch.zeros_like(X)
            parts["inertia"][:v] = inertia
        absolute = cfg.elastic_projection == "abs" or (cfg.elastic_projection == "auto" and not cfg.static)
        elastic_projection = ("abs" if absolute else "clamp") if project else "none"

        e = self.energies
        rest = self.rest
        in_kernel = cfg.membrane_filter == "stress"  # the membrane's Hessians are made PSD in the kernel
        membrane = e.membrane(
            x, self.faces, rest.rest_inv, rest.rest_area, self.membrane_mu, self.membrane_lambda,
            stress_filter=elastic_projection if in_kernel else "none",
        )  # fmt: skip
        add(self.faces, membrane, "membrane", "none" if in_kernel else elastic_projection)
        bending = e.bending(x, self.hinges, rest.rest_angle, rest.rest_weight, self.k_bend)
        add(self.hinges, bending, "bending", elastic_projection)
        if candidates.pt.shape[0] or candidates.ee.shape[0]:
            # Derivatives only for the active pairs (within d̂), which the distance-only kernels pick, with the pairs
            # within REACH · d̂ that a pattern miss grows the sparsity pattern by. On skirt7271 walking the active
            # pairs are a tenth of those whose boxes lie within d̂ of X.
            dhat2 = cfg.contact_distance**2
            c = candidates
            if active is None:
                pt_active, ee_active, pt_reach, ee_reach = self.active_rows(X, c, reach=True)
                pt_reach, ee_reach = c.pt[pt_reach], c.ee[ee_reach]
            else:
                pt_active, ee_active = active
            pt_pairs, ee_pairs = c.pt[pt_active], c.ee[ee_active]
            if active is not None:
                pt_reach, ee_reach = pt_pairs, ee_pairs
            pt, ee = e.contact(X, pt_pairs, ee_pairs, c.ee_eps[ee_active], dhat2, ctx.kappa)
            for index, reach, terms in ((pt_pairs, pt_reach, pt), (ee_pairs, ee_reach, ee)):
                add(index, terms, "contact", "clamp" if project else "none", reach=reach)
        if ctx.friction is not None and ctx.friction.index.shape[0]:
            f_energy, f_grad, f_hess = friction_potential(
                X - ctx.x_start, ctx.friction, cfg.friction_velocity * ctx.dt, True
            )
            index = ctx.friction.index.to(torch.int32)
            add(index, element_terms.ElementTerms(f_energy, f_grad, f_hess), "friction", "none")  # PSD already
        # the element terms scaled once, as :meth:`energy` sums them
        energy = energy + dt2 * torch.cat(term_energies).sum()
        grad = term_grad.mul_(dt2)
        grad[:v] += inertia
        return energy, grad, elements

    def active_rows(
        self, X: torch.Tensor, candidates: ContactPairs, capacity: tuple[int, int] | None = None, reach: bool = False
    ) -> tuple[torch.Tensor, ...]:
        """Rows of ``candidates``' point–triangle and edge–edge pairs within ``d̂`` at ``X`` (the active barrier pairs),
        by the distance-only kernels; with ``reach``, then the rows within ``REACH · d̂``.

        With ``capacity`` (no reach), exactly that many rows of each, the last candidate row (a phantom pair:
        :class:`~physavatar.cloth.newton_loop.NewtonLoop`) filling the rest, and then the ``[2]`` counts of active
        pairs, all without a read from the device; else exactly the rows selected (a read)."""
        dhat2 = self.config.contact_distance**2
        d_pt = ipc_barrier.point_triangle_distance_value(X, candidates.pt)
        d_ee = ipc_barrier.edge_edge_distance_value(X, candidates.ee)
        if capacity is not None:
            masks = (d_pt < dhat2, d_ee < dhat2)
            rows = [compact_rows(mask, size) for mask, size in zip(masks, capacity, strict=True)]
            return *rows, torch.stack([mask.sum() for mask in masks])
        limits = (dhat2, REACH**2 * dhat2) if reach else (dhat2,)
        return tuple(compact_rows(d < limit) for limit in limits for d in (d_pt, d_ee))

    def energy(self, X: torch.Tensor, near: ContactPairs, ctx: StepContext) -> torch.Tensor:
        """The incremental potential ``E(X)`` of :meth:`evaluate` alone (0-d), from the energy-only kernels: what
        the line search compares, without the element derivatives. ``near`` may be any superset of the pairs within
        ``d̂`` (the others add exact zeros): the line search passes the sweep's candidates unfiltered."""
        cfg, dt2 = self.config, ctx.dt * ctx.dt
        v = self.vertex_count
        x = X[:v].contiguous()
        if cfg.static:
            energy = -dt2 * (self.mass[:, None] * self.gravity * x).sum()
        else:
            r = (x - ctx.x_hat) * (~ctx.kinematic[:v])[:, None]
            energy = 0.5 * (self.mass[:, None] * r * r).sum()
        e, rest = self.energies, self.rest
        terms = [
            e.membrane_value(x, self.faces, rest.rest_inv, rest.rest_area, self.membrane_mu, self.membrane_lambda),
            e.bending_value(x, self.hinges, rest.rest_angle, rest.rest_weight, self.k_bend),
        ]
        if near.pt.shape[0] or near.ee.shape[0]:
            terms.extend(e.contact_value(X, near.pt, near.ee, near.ee_eps, cfg.contact_distance**2, ctx.kappa))
        if ctx.friction is not None and ctx.friction.index.shape[0]:
            terms.append(friction_potential(X - ctx.x_start, ctx.friction, cfg.friction_velocity * ctx.dt, False)[0])
        return energy + dt2 * torch.cat(terms).sum()
