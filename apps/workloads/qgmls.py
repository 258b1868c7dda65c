"""Q-GMLS simulation: IP assembly (energy, gradient, PSD Hessian) and a whole implicit step.

The reference swaps the Warp material-point kernel for its pure torch form (autograd Hessians,
eigen-projection); the contractions and the dense Cholesky are shared torch code in both. On CUDA the step
runs its device loop, one CUDA graph per step (:meth:`pienerf.sim.solver.SolverQGMLS.step`); the reference's torch
material response reads the device from the host, so its step runs the host loop. The assembly is measured as that
loop runs it too: replayed as a CUDA graph on CUDA, called on the CPU, with the Hessian's block products in the
solver's default precision for the device (:attr:`pienerf.sim.solver.SolverConfig.hessian_precision`: float32 on CUDA,
float64 on the CPU); ``qgmls_assemble_f64`` forms them in float64 beside it.
"""

from __future__ import annotations

import dataclasses

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.reference.hyperelastic import material_response_batched
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.solver import PointTargets, QGMLSControl, SolverConfig, SolverQGMLS

KERNELS = {"smoke": 16, "paper": 78, "large": 200}


def _box_model(size: str) -> QGMLSModel:
    """A 2:1:1 box of lattice particles, about 25 particles per kernel."""
    n = KERNELS[size]
    spacing = (0.016 / (25 * n)) ** (1 / 3)
    axes = [torch.arange(0.5 * spacing, extent, spacing, dtype=torch.float64) for extent in (0.4, 0.2, 0.2)]
    position = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    volume = torch.full((position.shape[0],), spacing**3, dtype=torch.float64)
    return QGMLSModel(position, volume, DiscretizationConfig(kernel_count=n), device=backend.torch_device())


def _deformed(model: QGMLSModel) -> torch.Tensor:
    """A smooth non-trivial configuration: a bend of a few degrees."""
    generator = torch.Generator().manual_seed(0)
    q = 1e-3 * torch.randn(model.shape_count, 3, generator=generator, dtype=torch.float64)
    return q.to(model.device)


def _pin_and_tip(model: QGMLSModel):
    """Handles of the box's pinned end (the particles within 3 cm of x = min) and of its far tip (one particle)."""
    pin = model.handle(model.position[model.position[:, 0] < model.position[:, 0].min() + 0.03])
    return pin, model.handle(model.position[model.position[:, 0].argmax()].unsqueeze(0))


def _params(model: QGMLSModel) -> dict:
    return {**model.summary(), "material": "neo_hookean", "dtype": "float64"}


def _assemble_case(device: str, size: str, product_dtype: torch.dtype) -> Case:
    """One evaluation (energy, gradient, PSD Hessian) as the solver's device loop runs it: on CUDA a replay of its
    CUDA graph (:class:`kernels.backend.CapturedCall`, q in a buffer that stays put), on the CPU a plain call. The
    reference is the eager evaluation with the torch material response, in float64."""
    model = _box_model(size)
    material = Material()
    kernel = model.integrator(material, product_dtype)
    reference = model.integrator(material)
    reference.response = material_response_batched
    q = _deformed(model)
    captured = device == "cuda"
    run = backend.CapturedCall(lambda: kernel.evaluate(q), capture=captured)
    return Case(
        run=run,
        reference=lambda: reference.evaluate(q),
        params={**_params(model), "captured": captured, "product_dtype": str(product_dtype).removeprefix("torch.")},
        work=1.0,
        unit="assemblies/s",
        reference_name="torch autograd material response",
    )


@workload("qgmls_assemble", "Q-GMLS IP integration: energy, gradient, PSD Hessian (n = 16 / 78 / 200 kernels)")
def bench_qgmls_assemble(device: str, size: str) -> Case:
    return _assemble_case(device, size, SolverConfig().hessian_product_dtype(device))


@workload("qgmls_assemble_f64", "as qgmls_assemble, the Hessian's block products in float64 on every device")
def bench_qgmls_assemble_f64(device: str, size: str) -> Case:
    return _assemble_case(device, size, torch.float64)


def _step_case(size: str, config: SolverConfig, name: str) -> Case:
    model = _box_model(size)
    solver = SolverQGMLS(model, Material(), config)
    # the reference cannot be captured (its material response reads the device), so it runs the host loop
    reference = SolverQGMLS(model, Material(), dataclasses.replace(config, device_loop=False))
    reference.step_integrator.response = material_response_batched
    pin, tip = _pin_and_tip(model)
    control = QGMLSControl(springs=[
        PointTargets(pin, pin.rest.clone(), 1e6),
        PointTargets(tip, tip.rest + torch.tensor([[0.0, 0.05, 0.0]], dtype=torch.float64, device=model.device), 1e3),
    ])
    state, scratch = solver.rest_state(), solver.rest_state()
    reports = []

    def step(s):
        reports.append(s.step(state, scratch, control, 1.0 / 60.0))

    case = Case(
        run=lambda: step(solver),
        reference=lambda: step(reference),
        params={**_params(model), "newton_iterations": config.newton_iterations,
                "hessian_updates": config.hessian_updates, "dt_s": 1.0 / 60.0},
        work=1.0,
        unit="steps/s",
        reference_name=name,
    )
    for _ in range(2):
        step(solver)
    last = reports[-1]
    case.extra.update({
        "time_assembly_s": last.time_assembly, "time_solve_s": last.time_solve, "time_other_s": last.time_other,
        "device_loop": last.device_loop, "time_device_loop_s": last.time_device_loop,
    })
    return case


@workload("qgmls_step", "Q-GMLS implicit Euler step, 3 Newton iterations, a drag and a pin (n = 16 / 78 / 200)")
def bench_qgmls_step(device: str, size: str) -> Case:
    config = SolverConfig(newton_iterations=3, newton_tolerance=0.0, rayleigh_alpha=1.0)
    return _step_case(size, config, "same step, host loop, torch material response")


@workload("qgmls_step_modified", "as qgmls_step, one Hessian factorisation reused by all 3 Newton iterations")
def bench_qgmls_step_modified(device: str, size: str) -> Case:
    config = SolverConfig(newton_iterations=3, newton_tolerance=0.0, rayleigh_alpha=1.0, hessian_updates=1)
    return _step_case(size, config, "same step, host loop, torch material response")


@workload("qgmls_step_reuse", "as qgmls_step along a drag moving 1 mm a step, a factor reused by up to 8 later steps")
def bench_qgmls_step_reuse(device: str, size: str) -> Case:
    """Each repetition steps the state on (the drag target rises 1 mm a step), so the kept factor ages as in a drag
    in the viewer; the record gives the share of steps that reused a factor and the refreshes."""
    config = SolverConfig(newton_iterations=3, newton_tolerance=0.0, rayleigh_alpha=1.0, factor_reuse=8)
    model = _box_model(size)
    pin, tip = _pin_and_tip(model)
    lift = torch.tensor([[0.0, 1e-3, 0.0]], dtype=torch.float64, device=model.device)
    solvers = {"run": SolverQGMLS(model, Material(), config),
               "reference": SolverQGMLS(model, Material(), dataclasses.replace(config, device_loop=False))}
    solvers["reference"].step_integrator.response = material_response_batched
    runs = {name: {"state": solver.rest_state(), "target": tip.rest.clone(), "reports": []}
            for name, solver in solvers.items()}

    extra = {}

    def step(name):
        run = runs[name]
        run["target"] += lift
        springs = [PointTargets(pin, pin.rest.clone(), 1e6), PointTargets(tip, run["target"], 1e3)]
        run["reports"].append(solvers[name].step(run["state"], run["state"], QGMLSControl(springs=springs), 1 / 60))
        reports = runs["run"]["reports"]
        extra.update(reused_share=sum(r.factor_reused for r in reports) / max(len(reports), 1),
                     factor_refreshes=solvers["run"].factor_refreshes, steps=len(reports))

    return Case(
        run=lambda: step("run"),
        reference=lambda: step("reference"),
        params={**_params(model), "newton_iterations": 3, "factor_reuse": 8, "dt_s": 1.0 / 60.0},
        work=1.0,
        unit="steps/s",
        reference_name="Newton, a factor each step, host loop, torch material response",
        extra=extra,
    )
