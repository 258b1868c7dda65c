"""Garment simulator (PhysAvatar §3.2): one implicit Codim-IPC step per repetition.

``cloth_step``: a DiffCloth skirt (7271 faces; 1252 at smoke size) on the procedural mannequin walking at 25 fps,
its waistband following the body's skinning, contact and friction on. ``cloth_step_large``: a sheet falling onto
a sphere.

Each repetition advances the same simulation by one frame (Δt = 0.04 s) from where the previous one left it, so
the timed steps move from free fall into contact; the phase shares in ``extra`` are those of the last step. The
reference runs the same solver with the element energies, gradients and Hessians from the autograd references
of :mod:`kernels.reference.cloth` (CCD, distances and the broad phase stay the kernels': the reference CCD is a
per-pair NumPy root finder, far too slow for a step).

``cloth_step`` at paper size takes the skirt7271 (3757 vertices) through the walk; its figures on GPU and CPU, and
what each change to the solver did to them, are on the measurements page ``docs/benchmarks.md``.
"""

from __future__ import annotations

import torch

from apps.workloads import Case, WorkloadUnavailable, workload
from kernels import backend
from kernels.element_terms import ElementTerms
from kernels.reference import cloth as ref
from physavatar.body import Body
from physavatar.cloth import PHASES, ClothConfig, ClothControl, ClothEnergies, SolverCloth
from physavatar.drive import BodyDriver
from physavatar.garment import SHARED_GARMENTS, load_garment, place_on_body, select_boundary
from physavatar.motion import walk
from physavatar.shapes import grid_sheet, icosphere

_SKIRT = {"smoke": "skirt1252.obj", "paper": "skirt7271.obj", "large": "skirt7271.obj"}

# vertices per side of the square sheet
_SIDE = {"smoke": 32, "paper": 224, "large": 224}
_DT = 0.04


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
        state = solver.initial_state()

        def run():
            stats = solver.step(state, state, control, _DT)
            if record:
                total = sum(stats.time.values()) or 1.0
                extra["newton_iterations"] = stats.newton_iterations
                extra["contacts"] = stats.contacts
                extra["phase_share"] = {k: round(v / total, 4) for k, v in stats.time.items()}
                extra["linear_solver"] = solver.linear_solver
            return state.x

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


@workload("cloth_step", "one Codim-IPC step of a skirt on the walking mannequin, contact on (frames/s)")
def bench_cloth_step(device: str, size: str) -> Case:
    path = SHARED_GARMENTS / _SKIRT[size]
    if not path.is_file():
        raise WorkloadUnavailable(
            f"cloth_step needs the DiffCloth skirt {path.name}, absent from {SHARED_GARMENTS}; "
            "put the project's shared data folder beside the checkout"
        )
    body = Body.mannequin(spacing=0.03)
    garment = place_on_body(load_garment(path), body)
    boundary = select_boundary(garment, body, mode="waist")
    motion = walk(body.skeleton)
    driver = BodyDriver.from_motion(body, motion, garment.vertices, boundary, motion.num_frames - 1)
    driver = driver.to(backend.torch_device())
    solver = SolverCloth(garment.vertices, garment.faces, ClothConfig(), body.faces)
    state = solver.initial_state()
    frame = [0]
    extra: dict = {"linear_solver": solver.linear_solver, "boundary_vertices": int(boundary.numel())}
    totals = dict.fromkeys(PHASES, 0.0)
    calls = [0]

    def run():
        t = frame[0]
        if t + 1 >= driver.frames:  # the clip is over: start it again from the rest pose
            fresh = solver.initial_state()
            state.x, state.v, t = fresh.x, fresh.v, 0
        stats = solver.step(state, state, driver.control(t), driver.dt)
        frame[0] = t + 1
        calls[0] += 1
        if calls[0] > 1:  # the first (warm-up) step compiles the kernels: its phases say nothing of the solver
            for key, value in stats.time.items():
                totals[key] += value
        total = sum(totals.values()) or 1.0
        extra["frame"] = t + 1
        extra["newton_iterations"] = stats.newton_iterations
        extra["contacts"] = stats.contacts
        extra["min_distance_body_m"] = stats.min_distance_body
        extra["phase_share"] = {k: round(v / total, 4) for k, v in totals.items()}
        return state.x

    return Case(
        run=run,
        reference=None,  # the autograd element energies take minutes per step at this size (see cloth_step_large)
        params={
            "garment": path.name,
            "vertices": int(garment.vertices.shape[0]),
            "faces": int(garment.faces.shape[0]),
            "body_faces": int(body.faces.shape[0]),
            "motion": "walk",
            "dt": driver.dt,
        },
        work=1.0,
        unit="frames/s",
        extra=extra,
    )
