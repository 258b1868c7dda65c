"""Garment simulator (PhysAvatar §3.2): one implicit Codim-IPC step per repetition.

``cloth_step``: a DiffCloth skirt (7271 faces; 1252 at smoke size) on the procedural mannequin walking at 25 fps,
its waistband following the body's skinning, contact and friction on. ``cloth_step_large``: a sheet falling onto
a sphere.

Each repetition advances the same simulation by one frame (Δt = 0.04 s) from where the previous one left it, so
the timed steps move from free fall into contact; the phase shares in ``extra`` are those of the last step. The
reference runs the same solver with the element energies, gradients and Hessians from the autograd references
of :mod:`kernels.reference.cloth` (CCD, distances and the broad phase stay the kernels': the reference CCD is a
per-pair NumPy root finder, far too slow for a step).

``cloth_step`` on an H100 (``--device cuda --size paper --reps 5``; 3757 vertices, cuDSS's sparse Cholesky): 90.3-93.8
ms per frame (10.7-11.1 frames/s; the history below, newest last). H100 machines vary by about ±30 % from one to the
next, so changes are compared on one machine, each code version in its own process, over frames 4-13 of the walk (the
same 81 Newton iterations). With the Newton matrices scattered by :mod:`kernels.assembly` onto a block pattern that
outlives the step: 109.3 ms per frame (13.5 ms per Newton iteration) against 149.7 ms (18.5 ms) with the COO assembly in
torch. With the Warp kernels launched through :func:`kernels.backend.launch` and fewer reads from the device (one per
candidate search, two fewer per Newton iteration), on a slower machine: 121.0 ms (14.9 ms) against 129-151 ms (16.0-18.6
ms, three runs). With phase times from CUDA events and the reads of an iteration merged: 100.0-102.0 ms against 110.7
ms. With the element Hessians PSD-filtered by cuSOLVER's batched Jacobi eigensolver (:mod:`kernels.cusolver`):
88.4-101.4 ms against 125.0 ms, and this benchmark 103.0 ms against 133.8 ms. With the contact derivatives taken for the
active pairs only (a tenth of the candidates near X), the barrier kernels went from 0.94 to 0.70 ms per Newton iteration
and the GPU's kernel time from 6.57 to 6.15 ms (CUPTI, frames 5-9), but the wall time did not move beyond the machine's
noise (this benchmark 97.8 and 104.0 ms): the loop is bound by the host's launches. With each Warp launch recorded once
and replayed (:func:`kernels.backend.launch`, about half the host time per launch), on a faster H100, three interleaved
runs each: 74.1 ms per frame (9.15 ms per Newton iteration) against 82.3 ms (10.16 ms). Phases over those frames (GPU
time between CUDA events): 47 % assembly (element Hessians, their batched eigen-filtering, the scatter), 24 % the sparse
solves (factorisation and solve), 19 % candidate searches and filtering, 6 % the line search, 3 % CCD, 1 % friction.
Before the Jacobi filter a Newton iteration kept the GPU busy 7.6 ms of its 12.5 (CUPTI, frames 14-18): 2.3 ms cuDSS
(1.9 ms of it the factorisation), 2.3 ms ``torch.linalg.eigh``, 0.9 ms the BVH candidate searches, 0.9 ms the barrier
kernels, the rest in about 390 small kernels, each launched from Python. The phase shares in ``extra`` leave out the
warm-up step, which compiles the kernels; with the float64 overloads of the generic kernels declared at import, it
builds them all, where the first contact used to rebuild the module (a 25 s step, and phase shares of 99 % assembly, in
this benchmark on a fresh H100: now 0.16 s at most, 99.0 ms median on a slower H100). On this project's 2-core CPU
(``--device cpu --reps 3``, SuperLU): 3.56 s per frame (3.66 s before the merged reads, 4.47 s with the COO assembly),
half of it in assembly (LAPACK's eigen-filtering most of it), 41 % in SuperLU, 8 % in the broad phase. The CPU runs the
exact contact lists, not the graphs below, so they leave its figure where it was: on a later day, two runs each, 3.91
and 3.94 s with the graph loop's version against 3.93 and 3.99 s before it (0.25 frames/s).

With the Newton iterations as four CUDA graphs over buffers that stay put (:class:`physavatar.cloth._NewtonLoop`) and 7
reads from the device a step instead of about 20, on one H100, each version in its own process, interleaved: this
benchmark ``--reps 5`` 93.8 and 90.3 ms against 102.5 and 105.0 ms, ``--reps 10`` 73.7 ms against 95.9 ms; frames 4-33
of the walk (179 Newton iterations, 53 candidate searches) 60.0 and 57.6 ms per frame (mean; medians 54.7 and 54.1)
against 71.2 ms (62.9). The loop is then bound by the device: its kernels take 34.3 ms of a frame's ~57 (CUPTI, frames
34-39, 3.7 Newton iterations a frame): the candidate searches 12.6 ms (37 %), cuDSS 8.4 ms (its factorisation 6.9 ms,
one kernel of 1.8 ms per Newton iteration), the batched Jacobi eigensolver 4.4 ms, the barrier kernels 2.7 ms. Over
the whole 4-s walk (99 frames, CPU run) the skirt takes 495 Newton iterations, 5.0 a frame (9.6 in frames 1-10, 4.5
after). ``cloth_step_large`` ``--reps 3``: 562 ms per frame, 6.7x its reference (3.78 s), on the same machine.

``cloth_step_large`` on an H100 (``--device cuda --size paper --reps 3``; 50,176 vertices, 99,458 faces, cuDSS):
449.4 ms per frame (2.23 frames/s), 7.4x the reference (3.34 s); 824.3 ms before the merged reads, the Jacobi filter
and the contact derivatives of the active pairs only (929.6 ms with the COO assembly; 5.10 s with block-Jacobi CG,
which needed thousands of iterations per solve). The default 10 repetitions reach the frames where the sheet lies on
the sphere: median 3.17 s per frame (0.32-5.76 s), about the reference's 3.31 s, since the solver's own work, not the
element energies, then dominates. Measured before those changes, 3 repetitions: 50 Newton iterations and 7119
contacts on the last step, whose time went 63 % to assembly, 24 % to the solves, 9 % to the broad phase and 4 % to the
line search. In those frames self-contacts kept joining vertices the Newton matrix's pattern lacked, and each growth
cost cuDSS a new analysis of 520-580 ms (150k DOFs; a factorisation takes 20 ms): frames 7-10 of 11 took 3.53, 5.86,
6.30 and 4.27 s with 1, 5, 6 and 5 analyses. Bounding the missing blocks on the diagonal and growing the pattern once,
at the next step (:mod:`kernels.assembly`), they take 2.98, 3.48, 2.73 and 1.77 s with 0, 1, 1 and 1 analyses and the
same Newton iterations (50, 50, 36, 21 against 50, 50, 36, 22), on one H100; frames 2-10 together 22.4 s against
31.6 s.
"""

from __future__ import annotations

import torch

from apps.workloads import Case, WorkloadUnavailable, workload
from kernels import backend, cloth
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

    def membrane(x, faces, rest_inv, rest_area, mu, lam, project=False, stress_filter="none"):
        terms = cloth.ElementTerms(*ref.membrane_energy(x, faces, rest_inv, rest_area, mu, lam, stress_filter))
        return terms._replace(hess=cloth.project_psd(terms.hess)) if project else terms

    def bending(x, hinges, rest_angle, rest_weight, k_bend, project=False):
        terms = cloth.ElementTerms(*ref.bending_energy(x, hinges, rest_angle, rest_weight, k_bend))
        return terms._replace(hess=cloth.project_psd(terms.hess)) if project else terms

    def contact(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness, project=False):
        pt = cloth.ElementTerms(*ref.point_triangle_barrier(x, pt_pairs, dhat, stiffness))
        ee = cloth.ElementTerms(*ref.edge_edge_barrier(x, ee_pairs, ee_eps_x, dhat, stiffness))
        if project:
            pt, ee = (t._replace(hess=cloth.project_psd(t.hess)) for t in (pt, ee))
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
