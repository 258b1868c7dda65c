"""Garment simulator (PhysAvatar §3.2): one implicit Codim-IPC step per repetition, and a peer simulator beside it.

``cloth_step``: a DiffCloth skirt (7271 faces; 1252 at smoke size) on the procedural mannequin walking at 25 fps,
its waistband following the body's skinning, contact and friction on. ``cloth_step_large``: a sheet falling onto
a sphere.

Each repetition advances the same simulation by one frame (Δt = 0.04 s) from where the previous one left it, so
the timed steps move from free fall into contact; the phase shares in ``extra`` are those of the last step. The
reference runs the same solver with the element energies, gradients and Hessians from the autograd references
of :mod:`kernels.reference.cloth` (CCD, distances and the broad phase stay the kernels': the reference CCD is a
per-pair NumPy root finder, far too slow for a step).

``cloth_step_newton``: the peer, NVIDIA Newton 1.8's ``SolverVBD`` (vertex block descent, self-contact on) on the
same skirt, the same mannequin mesh as Newton's kinematic mesh collider (its vertices moved by the same skinning,
:class:`~physavatar.drive.BodyDriver`, linearly within a frame, every substep), the same walk at the same 25 fps,
and the waist vertices as kinematic particles on the same driven targets. Newton is optional (``pip install -e
'.[peers]'``); without it the workload is skipped and says so. Settings from Newton's example
``cloth/example_cloth_poker_cards.py``, the one of its cloth examples in metres with SolverVBD, a kinematic
collider and self-contact: 20 substeps a frame and 10 VBD iterations each, a particle radius of 3 mm (the contact
thickness against the body), a self-contact margin of 1 mm with 0.5 mm more for detection, the topological
contact filter of 2 rings, soft-contact stiffness 1e5 N/m and damping 1e2, the collision pipeline's soft-contact
gap of 5 mm; the friction coefficient is ours (0.2), the example's 0.3 is not. Material, mapped from
:class:`~physavatar.cloth.ClothConfig` (:func:`_newton_membrane`, :func:`_newton_hinge_stiffness`): areal density
``ρ h``; membrane Lamé parameters ``h μ``, ``h λ`` (plane stress; Newton's stable Neo-Hookean membrane agrees with
our StVK at small strain only); each hinge's stiffness set so that Newton's ``½ k_e ‖ē‖ (θ − θ̄)²`` equals our
``k w̄ (θ − θ̄)²``; no material damping, as ours has none. What Newton cannot match: its body contact is a penalty
(a stiffness acting within the 3 mm particle radius) and its self-contact a penalty whose moves are truncated to
stay apart, where ours is an IPC barrier with CCD that keeps every pair apart by construction, so Newton's garment
may press into the body; its time step is 20 explicit substeps of VBD
iterations, not one converged implicit Euler step; its collider is the body mesh at one position per substep, not
swept continuously as our CCD sweeps it; it runs in float32, ours in float64.

Both skirt workloads carry in their records ``realtime_factor`` (0.04 s over the median seconds per frame) and,
measured after every frame (untimed, :attr:`~apps.workloads.Case.observe`) by this project's own distance
kernels (:func:`physavatar.cloth.contact.garment_distances`) on either simulator's positions:
``min_distance_body`` and ``min_distance_self`` (m, the smallest over the frames run; garment pairs that share a
vertex left out; ``None`` where nothing came within 1 cm) and ``vertices_inside_body`` (the most over the frames, by
the body's winding number). ``cloth_step``'s also carries ``steps``, ``steps_converged`` (steps that met the Newton
tolerance with every kinematic vertex on its target) and ``newton_iterations_total`` over every step run.

``rollout_backward``: the adjoint of a 24-frame rollout (:func:`physavatar.cloth.rollout`; 6 frames at smoke size)
of ``cloth_step``'s skirt on the walk, in the estimation's fabric (:data:`physavatar.fit.estimation.SYNTHETIC_FABRIC`):
``∂L/∂(ρ, κ_s, κ_b, v₀)`` of ``L = ½ Σ ‖x_t‖²``, one adjoint solve per step. The reference is the forward rollout it
differentiates, so ``speedup_vs_reference`` is forward over backward time (its inverse is the backward's cost in
forwards); ``extra`` carries the memory the forward keeps for the backward per frame.

``cloth_step`` at paper size takes the skirt7271 (3757 vertices) through the walk; its figures on GPU and CPU, and
what each change to the solver did to them, are on the measurements page ``docs/benchmarks.md``, as are the peer's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from apps.workloads import Case, WorkloadUnavailable, workload
from kernels import backend
from kernels.element_terms import ElementTerms
from kernels.reference import cloth as ref
from kernels.shell import plane_stress_lame
from physavatar.body import Body, walk
from physavatar.cloth import (
    PHASES,
    ClothConfig,
    ClothControl,
    ClothEnergies,
    RolloutScene,
    SolverCloth,
    bending_stiffness,
    rollout,
)
from physavatar.cloth.contact import garment_distances
from physavatar.drive import BodyDriver
from physavatar.fit.estimation import SYNTHETIC_FABRIC
from physavatar.garment import SHARED_GARMENTS, load_garment, place_on_body, select_boundary
from physavatar.shapes import grid_sheet, icosphere

_SKIRT = {"smoke": "skirt1252.obj", "paper": "skirt7271.obj", "large": "skirt7271.obj"}

# vertices per side of the square sheet
_SIDE = {"smoke": 32, "paper": 224, "large": 224}
_DT = 0.04
_REACH = 1e-2
"""Distances up to this (m) are measured exactly; the records say ``None`` where nothing came that close."""
_PEERS_FIX = "pip install -e '.[peers]'"

# Newton's settings, from its example ``cloth/example_cloth_poker_cards.py`` (SolverVBD, metres, a kinematic collider
# and self-contact): substeps per frame and VBD iterations per substep, the particle radius (the contact thickness
# against the body), the self-contact margin and detection gap, the topological contact filter, the soft-contact
# penalty and damping and the collision pipeline's soft-contact gap.
_NEWTON_SUBSTEPS = 20
_NEWTON_ITERATIONS = 10
_NEWTON_PARTICLE_RADIUS = 3e-3
_NEWTON_SELF_CONTACT_MARGIN = 1e-3
_NEWTON_SELF_CONTACT_GAP = 5e-4
_NEWTON_TOPOLOGICAL_FILTER = 2
_NEWTON_CONTACT_KE = 1e5
_NEWTON_CONTACT_KD = 1e2
_NEWTON_SOFT_CONTACT_GAP = 5e-3


def _sheet(n: int, width: float, height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``n × n`` vertices spanning ``width`` in x and z at ``height``, centred on the y axis."""
    x, faces = grid_sheet(n, n, width / (n - 1))
    return torch.stack([x[:, 0] - 0.5 * width, torch.full_like(x[:, 0], height), x[:, 1] - 0.5 * width], 1), faces


def _reference_energies() -> ClothEnergies:
    """The solver's element evaluators with values, gradients and Hessians from the autograd references."""

    def membrane(x, faces, rest_inv, rest_area, mu, lam, stress_filter="none"):
        return ElementTerms(*ref.membrane_energy(x, faces, rest_inv, rest_area, mu, lam, stress_filter))

    def bending(x, hinges, rest_angle, rest_weight, k_bend):
        return ElementTerms(*ref.bending_energy(x, hinges, rest_angle, rest_weight, k_bend))

    def contact(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness):
        pt = ElementTerms(*ref.point_triangle_barrier(x, pt_pairs, dhat, stiffness))
        ee = ElementTerms(*ref.edge_edge_barrier(x, ee_pairs, ee_eps_x, dhat, stiffness))
        return pt, ee

    def membrane_value(*args):
        return membrane(*args).energy

    def bending_value(*args):
        return bending(*args).energy

    def contact_value(*args):
        return tuple(terms.energy for terms in contact(*args))

    return ClothEnergies(membrane, bending, contact, membrane_value, bending_value, contact_value)


@workload("cloth_step_large", "one Codim-IPC garment step: a sheet falling onto a sphere (frames/s)")
def bench_cloth_step_large(device: str, size: str) -> Case:
    n = _SIDE[size]
    x, faces = _sheet(n, 1.0, 0.34)
    body, body_faces = icosphere(3, 0.3)
    config = ClothConfig()
    body = body.to(backend.torch_device())
    empty = torch.zeros(0, dtype=torch.int64, device=body.device)
    control = ClothControl(body, body, empty, torch.zeros(0, 3, dtype=torch.float64, device=body.device))
    extra: dict = {}

    def stepper(energies: ClothEnergies | None, record: bool):
        solver = SolverCloth(x, faces, config, body_faces, energies=energies)
        states = [solver.initial_state(), solver.initial_state()]  # double-buffered: each step writes the other

        def run():
            stats = solver.step(states[0], states[1], control, _DT)
            states.reverse()
            if record:
                total = sum(stats.time.values()) or 1.0
                extra["newton_iterations"] = stats.newton_iterations
                extra["contacts"] = stats.contacts
                extra["phase_share"] = {k: round(v / total, 4) for k, v in stats.time.items()}
                extra["linear_solver"] = solver.linear_solver
            return states[0].x

        return run

    return Case(
        run=stepper(None, True),
        reference=stepper(_reference_energies(), False),
        params={"vertices": n * n, "faces": int(faces.shape[0]), "body_faces": int(body_faces.shape[0]), "dt": _DT},
        work=1.0,
        unit="frames/s",
        reference_name="autograd element energies (kernels.reference.cloth)",
        extra=extra,
    )


@dataclass(frozen=True)
class _WalkingSkirt:
    """The garment scene both ``cloth_step`` and ``cloth_step_newton`` run: a DiffCloth skirt on the walking
    mannequin, its waistband driven by the skinning."""

    path: Path  # the garment file
    faces: torch.Tensor  # [F, 3] garment triangles
    body_faces: torch.Tensor  # [Fb, 3] mannequin triangles
    x_rest: torch.Tensor  # [V, 3] garment rest positions, m
    boundary: torch.Tensor  # [D] waist vertices
    driver: BodyDriver

    @staticmethod
    def load(workload_name: str, size: str) -> _WalkingSkirt:
        path = SHARED_GARMENTS / _SKIRT[size]
        if not path.is_file():
            raise WorkloadUnavailable(
                f"{workload_name} needs the DiffCloth skirt {path.name}, absent from {SHARED_GARMENTS}; "
                "put the project's shared data folder beside the checkout"
            )
        body = Body.mannequin(spacing=0.03)
        garment = place_on_body(load_garment(path), body)
        boundary = select_boundary(garment, body, mode="waist")
        motion = walk(body.skeleton)
        driver = BodyDriver.from_motion(body, motion, garment.vertices, boundary, motion.num_frames - 1)
        return _WalkingSkirt(path, garment.faces, body.faces, garment.vertices, boundary, driver)

    def params(self) -> dict:
        return {
            "garment": self.path.name,
            "vertices": int(self.x_rest.shape[0]),
            "faces": int(self.faces.shape[0]),
            "body_faces": int(self.body_faces.shape[0]),
            "motion": "walk",
            "dt": self.driver.dt,
        }

    def distance_tracker(self, extra: dict):
        """``observe(x, frame)``: measures garment positions ``x [V, 3]`` at ``frame`` with
        :func:`~physavatar.cloth.contact.garment_distances` and keeps, in ``extra``, the smallest distances (m) and
        the most vertices inside the body over the frames seen."""
        seen = {"body": math.inf, "self": math.inf, "inside": 0}

        def observe(x: torch.Tensor, frame: int) -> None:
            d = garment_distances(x, self.faces, self.driver.body_frames[frame], self.body_faces, _REACH)
            seen["body"], seen["self"] = min(seen["body"], d.body), min(seen["self"], d.garment)
            seen["inside"] = max(seen["inside"], d.inside)
            extra["min_distance_body"] = seen["body"] if math.isfinite(seen["body"]) else None
            extra["min_distance_self"] = seen["self"] if math.isfinite(seen["self"]) else None
            extra["vertices_inside_body"] = seen["inside"]

        return observe


@workload("cloth_step", "one Codim-IPC step of a skirt on the walking mannequin, contact on (frames/s)")
def bench_cloth_step(device: str, size: str) -> Case:
    scene = _WalkingSkirt.load("cloth_step", size)
    driver = scene.driver.to(backend.torch_device())
    solver = SolverCloth(scene.x_rest, scene.faces, ClothConfig(), scene.body_faces)
    states = [solver.initial_state(), solver.initial_state()]  # double-buffered: each step writes the other
    frame = [0]
    extra: dict = {"linear_solver": solver.linear_solver, "boundary_vertices": int(scene.boundary.numel())}
    totals = dict.fromkeys(PHASES, 0.0)
    calls = [0]
    track = scene.distance_tracker(extra)

    def run():
        t = frame[0]
        if t + 1 >= driver.frames:  # the clip is over: start it again from the rest pose
            states[0].x.copy_(solver.x_rest)
            states[0].v.zero_()
            t = 0
        stats = solver.step(states[0], states[1], driver.control(t), driver.dt)
        states.reverse()
        frame[0] = t + 1
        calls[0] += 1
        if calls[0] > 1:  # the first (warm-up) step compiles the kernels: its phases say nothing of the solver
            for key, value in stats.time.items():
                totals[key] += value
        total = sum(totals.values()) or 1.0
        extra["frame"] = t + 1
        extra["newton_iterations"] = stats.newton_iterations
        extra["contacts"] = stats.contacts
        extra["steps"] = extra.get("steps", 0) + 1
        extra["steps_converged"] = extra.get("steps_converged", 0) + int(stats.converged)
        extra["newton_iterations_total"] = extra.get("newton_iterations_total", 0) + stats.newton_iterations
        extra["phase_share"] = {k: round(v / total, 4) for k, v in totals.items()}
        return states[0].x

    return Case(
        run=run,
        reference=None,  # the autograd element energies take minutes per step at this size (see cloth_step_large)
        params=scene.params(),
        work=1.0,
        unit="frames/s",
        extra=extra,
        frame_seconds=driver.dt,
        observe=lambda: track(states[0].x, frame[0]),
    )


@workload("rollout_backward", "adjoint of a 24-frame skirt rollout through contact, beside its forward (backward/s)")
def bench_rollout_backward(device: str, size: str) -> Case:
    scene = _WalkingSkirt.load("rollout_backward", size)
    frames = 6 if size == "smoke" else 24
    dev = backend.torch_device()
    driver = scene.driver.to(dev)
    body, targets = driver.body_frames[:frames], driver.boundary_targets[:frames]
    setting = RolloutScene(
        scene.x_rest.to(dev), scene.faces.to(dev), scene.body_faces.to(dev), scene.boundary.to(dev), driver.dt,
        SYNTHETIC_FABRIC,
    )
    fabric = SYNTHETIC_FABRIC
    params = [
        torch.tensor(value, dtype=torch.float64, device=dev, requires_grad=True)
        for value in (fabric.density, fabric.kappa_s, fabric.kappa_b)
    ]
    velocity = torch.zeros_like(setting.rest_vertices, dtype=torch.float64, requires_grad=True)

    def forward():
        return rollout(setting, *params, setting.rest_vertices, body, targets, velocity=velocity)

    loss = 0.5 * forward().square().sum()
    vertices = int(scene.x_rest.shape[0])

    def backward():
        return torch.autograd.grad(loss, [*params, velocity], retain_graph=True)

    extra = {"forward_frames_bytes_per_frame": 24 * vertices, "frames": frames}
    return Case(
        run=backward,
        reference=forward,
        params={**scene.params(), "frames": frames, "fabric": "SYNTHETIC_FABRIC"},
        work=1.0,
        unit="backward/s",
        reference_name="the forward rollout it differentiates",
        extra=extra,
    )


def _newton_membrane(config: ClothConfig) -> tuple[float, float, float]:
    """Newton's ``(density, tri_ke, tri_ka)`` for the project's material (SI units).

    Newton's density is per area: ``ρ h``, kg/m² (both lump a third of each triangle's mass on its vertices).
    ``tri_ke``, ``tri_ka`` are the Lamé parameters of Newton's membrane (stable Neo-Hookean, Smith et al. 2018, whose
    small-strain limit is the project's StVK) per unit area: the thickness-integrated plane-stress ``h μ``, ``h λ``
    of ``E = κ_s E₀`` and ``ν`` (:func:`kernels.shell.plane_stress_lame`), N/m.
    """
    mu, lam = plane_stress_lame(config.young, config.poisson, config.thickness)
    return config.density * config.thickness, mu, lam


def _newton_hinge_stiffness(config: ClothConfig, x_rest: torch.Tensor, edge_indices: torch.Tensor) -> torch.Tensor:
    """``[E]`` Newton's per-edge bending stiffness ``k_e`` (N) that gives each hinge the project's energy.

    Newton's hinge energy is ``½ k_e ‖ē‖ (θ − θ̄)²``, the project's ``k w̄ (θ − θ̄)²`` with ``w̄ = 3‖ē‖²/Ā`` (``Ā``
    the two rest triangle areas, ``k`` from :func:`~physavatar.cloth.bending_stiffness`), so ``k_e = 6 k ‖ē‖ / Ā``;
    0 on boundary edges (no second triangle).

    Args:
        config: the project's material.
        x_rest: ``[V, 3]`` rest positions, m.
        edge_indices: ``[E, 4]`` Newton's bending edges: the two opposite vertices (``-1`` where missing), then the
            edge's two ends.
    """
    e = edge_indices.long()
    x = x_rest.to(torch.float64)
    a, b = x[e[:, 2]], x[e[:, 3]]
    o0, o1 = x[e[:, 0].clamp(min=0)], x[e[:, 1].clamp(min=0)]
    area = 0.5 * (torch.linalg.cross(b - a, o0 - a).norm(dim=1) + torch.linalg.cross(b - a, o1 - a).norm(dim=1))
    k_e = 6.0 * bending_stiffness(config) * (b - a).norm(dim=1) / area.clamp(min=1e-30)
    return torch.where((e[:, 0] >= 0) & (e[:, 1] >= 0), k_e, torch.zeros_like(k_e))


@workload("cloth_step_newton", "peer: Newton 1.8's SolverVBD on cloth_step's skirt and walk (frames/s)")
def bench_cloth_step_newton(device: str, size: str) -> Case:
    try:  # Newton is an optional peer (the 'peers' extra), imported only by this workload
        import newton
        import warp as wp
    except ImportError as error:
        raise WorkloadUnavailable(f"cloth_step_newton needs NVIDIA Newton 1.8 ({error}); {_PEERS_FIX}") from error
    scene = _WalkingSkirt.load("cloth_step_newton", size)
    config = ClothConfig()
    wp_device = backend.warp_device()
    torch_device = backend.torch_device()
    driver = scene.driver.to(torch_device)
    body_frames = driver.body_frames.to(torch.float32)
    targets = driver.boundary_targets.to(torch.float32)
    pinned = driver.boundary_index

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=config.gravity)
    density, tri_ke, tri_ka = _newton_membrane(config)
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=scene.x_rest.tolist(),
        indices=scene.faces.reshape(-1).tolist(),
        density=density,
        tri_ke=tri_ke,
        tri_ka=tri_ka,
        tri_kd=0.0,  # the project's material has no damping (implicit Euler's own only)
        edge_ke=1.0,  # replaced per edge below, once Newton has made its bending edges
        edge_kd=0.0,
        particle_radius=_NEWTON_PARTICLE_RADIUS,
    )
    body = newton.Mesh(body_frames[0].cpu().numpy(), scene.body_faces.reshape(-1).cpu().numpy(), compute_inertia=False)
    builder.add_shape_mesh(body=-1, mesh=body, cfg=newton.ModelBuilder.ShapeConfig(mu=config.friction))
    builder.color()
    model = builder.finalize(device=wp_device)
    hinge = _newton_hinge_stiffness(config, scene.x_rest, wp.to_torch(model.edge_indices).cpu())
    wp.to_torch(model.edge_bending_properties)[:, 0] = hinge.to(torch_device, torch.float32)
    model.soft_contact_ke = _NEWTON_CONTACT_KE
    model.soft_contact_kd = _NEWTON_CONTACT_KD
    model.soft_contact_mu = config.friction
    flags = wp.to_torch(model.particle_flags)
    flags[pinned] &= ~int(newton.ParticleFlags.ACTIVE)  # the waist is kinematic: positions written every substep
    solver = newton.solvers.SolverVBD(
        model,
        iterations=_NEWTON_ITERATIONS,
        particle_enable_self_contact=True,
        particle_self_contact_margin=_NEWTON_SELF_CONTACT_MARGIN,
        particle_self_contact_gap=_NEWTON_SELF_CONTACT_GAP,
        particle_topological_contact_filter_threshold=_NEWTON_TOPOLOGICAL_FILTER,
    )
    collision = newton.CollisionPipeline(model, soft_contact_gap=_NEWTON_SOFT_CONTACT_GAP)
    contacts = collision.contacts()
    states = [model.state(), model.state()]
    control = model.control()
    # the body mesh's points and velocities and its box in the broad phase, moved by the skinning every substep
    points, velocities = wp.to_torch(body.mesh.points), wp.to_torch(body.mesh.velocities)
    box_lo, box_hi = wp.to_torch(model.shape_collision_aabb_lower), wp.to_torch(model.shape_collision_aabb_upper)
    substep = driver.dt / _NEWTON_SUBSTEPS
    frame = [0]
    extra: dict = {
        "boundary_vertices": int(pinned.numel()),
        "substeps": _NEWTON_SUBSTEPS,
        "iterations": _NEWTON_ITERATIONS,
        "newton_version": newton.__version__,
    }
    track = scene.distance_tracker(extra)

    def run():
        t = frame[0]
        if t + 1 >= driver.frames:  # the clip is over: start it again from the rest pose
            states[0].particle_q.assign(model.particle_q)
            states[0].particle_qd.zero_()
            t = 0
        b0, b1 = body_frames[t], body_frames[t + 1]
        box_lo[0] = torch.minimum(b0.amin(0), b1.amin(0))
        box_hi[0] = torch.maximum(b0.amax(0), b1.amax(0))
        velocities.copy_((b1 - b0) / driver.dt)
        solver.rebuild_bvh(states[0])
        for k in range(1, _NEWTON_SUBSTEPS + 1):
            s = k / _NEWTON_SUBSTEPS
            points.copy_(torch.lerp(b0, b1, s))
            body.mesh.refit()
            waist = torch.lerp(targets[t], targets[t + 1], s)
            for state in states:
                wp.to_torch(state.particle_q)[pinned] = waist
            states[0].clear_forces()
            collision.collide(states[0], contacts)
            solver.step(states[0], states[1], control, contacts, substep)
            states.reverse()
        frame[0] = t + 1
        extra["frame"] = t + 1
        return states[0].particle_q

    return Case(
        run=run,
        reference=None,  # the peer is measured beside cloth_step, not against a reference of its own
        params={**scene.params(), "simulator": "newton.solvers.SolverVBD", "particle_radius": _NEWTON_PARTICLE_RADIUS},
        work=1.0,
        unit="frames/s",
        reference_name="-",
        extra=extra,
        frame_seconds=driver.dt,
        observe=lambda: track(wp.to_torch(states[0].particle_q), frame[0]),
    )
