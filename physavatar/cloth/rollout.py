"""A garment rollout as a torch operation: frames forward by :meth:`SolverCloth.step`, gradients back by the adjoint.

:class:`ClothRollout` simulates ``T − 1`` implicit steps (PhysAvatar Eq. 5) from an initial state under given body
and boundary motion and returns the ``[T, V, 3]`` garment frames; its backward carries the loss's adjoint from the
last frame to the first, one linear solve with the converged step's exact Hessian per step (``docs/adjoint.md``
derives it). Differentiable inputs: the global density ``ρ`` and stiffness factors ``κ_s``, ``κ_b``, per-face
factors of them, and the initial velocity. The body, the boundary targets and the initial positions are not
(their gradients are ``None``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from kernels import backend, shell
from physavatar.cloth.config import ClothConfig
from physavatar.cloth.potential import bending_stiffness
from physavatar.cloth.solver import ClothControl, ClothState, SolverCloth, StepLinearisation

__all__ = ["ClothRollout", "RolloutScene", "rollout"]

F64 = torch.float64


@dataclass(frozen=True)
class RolloutScene:
    """What a rollout holds fixed: the garment, the body mesh, the boundary vertices, the step and the settings.

    Attributes:
        rest_vertices: ``[V, 3]`` garment rest positions, m.
        faces: ``[F, 3]`` garment triangles.
        body_faces: ``[Fb, 3]`` body collider triangles (may be empty: ``[0, 3]``).
        boundary_index: ``[D]`` int64 Dirichlet vertices (may be empty).
        dt: step size, s.
        config: solver settings; its ``density``, ``kappa_s`` and ``kappa_b`` are replaced by the rollout's inputs.
            Gradients are as accurate as the steps are converged: use a tight ``newton_tolerance``
            (``docs/adjoint.md``).
    """

    rest_vertices: torch.Tensor
    faces: torch.Tensor
    body_faces: torch.Tensor
    boundary_index: torch.Tensor
    dt: float
    config: ClothConfig


class ClothRollout(torch.autograd.Function):
    """``frames [T, V, 3] = rollout(ρ, κ_s, κ_b, s [F], b [F], v₀ [V, 3]; x₀, body, targets)`` with an adjoint backward.

    Forward: ``T − 1`` calls of :meth:`SolverCloth.step`; each must converge (else ``ValueError``). Backward, for
    steps ``t = T − 2 … 0`` (``docs/adjoint.md``): with ``ā`` the adjoint of ``x⁺ = x_{t+1}`` (the loss's
    gradient plus what the later steps hand back through ``x`` and ``v = (x⁺ − x)/Δt``), solve ``H λ = ā`` on the
    free DOFs (``H`` the exact, symmetric Hessian of the step's potential at ``x⁺``), then

    * parameters: ``θ̄ −= λ · ∂_θ∇E`` (the ``∂_θ∇E`` of :meth:`SolverCloth.sensitivity_step`; per face, the
      element gradients of membrane and bending);
    * previous state: ``x̄ += M λ + Δt² H_D λ``, ``v̄ += Δt M λ`` (inertia and lagged friction).

    Memory: the forward keeps the frames it returns (``24 V`` bytes per frame, float64) and the solver; nothing
    per contact or per Newton iteration. The backward recomputes each step's linearisation (one broad phase, one
    assembly, one factorisation and one single-right-hand-side solve per step) and holds one at a time: the Hessian
    of ``V`` free vertices, ``F`` faces, ``H ≈ 1.5 F`` hinges and ``C`` contacts and ``K`` friction pairs. The
    inputs ``body [T, B, 3]`` and ``targets [T, D, 3]`` are kept by reference (``24 (B + D)`` bytes per frame).

    Inputs (positional, as :func:`rollout` passes them): ``scene`` (:class:`RolloutScene`), ``density``,
    ``kappa_s``, ``kappa_b`` (0-d), ``kappa_s_field``, ``kappa_b_field`` (``[F]`` factors or ``None``),
    ``velocity`` (``[V, 3]``), ``x0`` (``[V, 3]``), ``body`` (``[T, B, 3]``), ``targets`` (``[T, D, 3]``).
    """

    @staticmethod
    def forward(ctx, scene, density, kappa_s, kappa_b, kappa_s_field, kappa_b_field, velocity, x0, body, targets):
        config = dataclasses.replace(
            scene.config, density=float(density), kappa_s=float(kappa_s), kappa_b=float(kappa_b)
        )
        solver = SolverCloth(scene.rest_vertices, scene.faces, config, scene.body_faces)
        solver.set_stiffness_fields(kappa_s_field, kappa_b_field)
        dev = solver.x_rest.device
        frames = x0.new_zeros(body.shape[0], *x0.shape, dtype=F64, device=dev)
        frames[0] = x0.detach().to(dev, F64)
        state = ClothState(frames[0].clone(), velocity.detach().to(dev, F64).clone())
        new = ClothState(state.x.clone(), state.v.clone())
        for t in range(body.shape[0] - 1):
            report = solver.step(state, new, _control(scene, body, targets, t, dev), scene.dt)
            if not report.converged:
                raise ValueError(
                    f"step {t + 1} did not converge ({report.newton_iterations} Newton iterations); the adjoint needs "
                    "converged steps: raise config.max_newton_iterations or loosen config.newton_tolerance"
                )
            state, new = new, state
            frames[t + 1] = state.x
        ctx.scene, ctx.solver = scene, solver
        ctx.fields = (kappa_s_field is not None, kappa_b_field is not None)
        inputs = (density, kappa_s, kappa_b, kappa_s_field, kappa_b_field, velocity)
        ctx.devices = [None if t is None else t.device for t in inputs]
        ctx.save_for_backward(frames, velocity, body, targets)
        return frames.to(x0.device)

    @staticmethod
    def backward(ctx, grad_frames):
        frames, velocity, body, targets = ctx.saved_tensors
        scene, solver = ctx.scene, ctx.solver
        grads = rollout_adjoint(solver, scene, frames, velocity, body, targets, grad_frames, *ctx.fields)
        wanted = ctx.needs_input_grad
        pairs = enumerate(zip(grads, ctx.devices, strict=True))
        out = [None] + [g.to(d) if wanted[i + 1] else None for i, (g, d) in pairs]
        return (*out, None, None, None)


def rollout_adjoint(
    solver: SolverCloth,
    scene: RolloutScene,
    frames: torch.Tensor,
    velocity: torch.Tensor,
    body: torch.Tensor,
    targets: torch.Tensor,
    grad_frames: torch.Tensor,
    kappa_s_field: bool = False,
    kappa_b_field: bool = False,
) -> tuple[torch.Tensor, ...]:
    """The adjoint of a rollout that ``solver`` ran: ``grad_frames [T, V, 3]`` back to its inputs.

    Args:
        solver: the solver of the forward, with its material and stiffness fields.
        scene: the rollout's scene.
        frames: ``[T, V, 3]`` the forward's frames, m.
        velocity: ``[V, 3]`` the initial velocity, m/s.
        body: ``[T, B, 3]`` body vertices per frame, m.
        targets: ``[T, D, 3]`` boundary targets per frame, m.
        grad_frames: ``[T, V, 3]`` ``∂L/∂frames``.
        kappa_s_field: also return ``∂L/∂s [F]`` (else ``None``).
        kappa_b_field: also return ``∂L/∂b [F]`` (else ``None``).

    Returns:
        ``(∂L/∂ρ, ∂L/∂κ_s, ∂L/∂κ_b, ∂L/∂s [F] or None, ∂L/∂b [F] or None, ∂L/∂v₀ [V, 3])``, 0-d and float64.
    """
    cfg, dt = solver.config, scene.dt
    dev = solver.x_rest.device
    v_count, dynamic = solver.vertex_count, not cfg.static
    frames = frames.detach().to(dev, F64)
    grad_frames = grad_frames.detach().to(dev, F64)
    mass = solver.potential.mass[:, None]
    theta = torch.zeros(3, dtype=F64, device=dev)
    face_count = solver.faces.shape[0]
    s_grad = torch.zeros(face_count, dtype=F64, device=dev) if kappa_s_field else None
    b_grad = torch.zeros(face_count, dtype=F64, device=dev) if kappa_b_field else None
    hinge_faces = shell.hinges_from_faces(solver.faces)[1] if kappa_b_field else None
    a_x = grad_frames[-1].clone()  # adjoint of the end state's positions, then of each earlier frame's
    a_v = torch.zeros_like(a_x)
    velocities = [velocity.detach().to(dev, F64)]
    velocities += [(frames[t + 1] - frames[t]) / dt for t in range(frames.shape[0] - 1)]
    for t in range(frames.shape[0] - 2, -1, -1):
        state_in = ClothState(frames[t], velocities[t])
        state_out = ClothState(frames[t + 1], velocities[t + 1] if dynamic else torch.zeros_like(frames[t]))
        lin = solver.linearise_step(state_in, state_out, _control(scene, body, targets, t, dev), dt)
        load = a_x + a_v / dt if dynamic else a_x  # v⁺ = (x⁺ − x)/Δt
        a_x = grad_frames[t] - a_v / dt if dynamic else grad_frames[t].clone()
        a_v = torch.zeros_like(a_x)
        lam = _adjoint_solve(solver, lin, load)
        theta -= _explicit_products(solver, lin, lam)
        x_end = lin.positions[:v_count].contiguous()
        if s_grad is not None:
            rest = solver.potential.rest
            mu, lam_lame = shell.plane_stress_lame(cfg.young, cfg.poisson, cfg.thickness)
            element = shell.membrane_energy(x_end, solver.faces, rest.rest_inv, rest.rest_area, mu, lam_lame).grad
            s_grad -= dt * dt * (lam[solver.faces.long()] * element).sum(dim=(1, 2))
        if b_grad is not None:
            rest, hinges = solver.potential.rest, solver.potential.hinges
            k = bending_stiffness(cfg)
            element = shell.bending_energy(x_end, hinges, rest.rest_angle, rest.rest_weight, k).grad
            per_hinge = dt * dt * (lam[hinges.long()] * element).sum(dim=(1, 2))
            b_grad.index_add_(0, hinge_faces.reshape(-1), -0.5 * per_hinge.repeat_interleave(2))
        if dynamic:
            a_x += mass * lam[:v_count]
            a_v += dt * mass * lam[:v_count]
            if lin.friction_hessian is not None:
                index = lin.friction.index
                k = index.shape[0]
                coupled = torch.bmm(lin.friction_hessian, lam[index].reshape(k, 12, 1)).reshape(k * 4, 3)
                full = torch.zeros_like(lam).index_add_(0, index.reshape(-1), dt * dt * coupled)
                a_x += full[:v_count]
    v_grad = a_v if dynamic else torch.zeros_like(a_v)
    return theta[0], theta[1], theta[2], s_grad, b_grad, v_grad


def rollout(
    scene: RolloutScene,
    density: torch.Tensor | float,
    kappa_s: torch.Tensor | float,
    kappa_b: torch.Tensor | float,
    x0: torch.Tensor,
    body: torch.Tensor | None = None,
    targets: torch.Tensor | None = None,
    velocity: torch.Tensor | None = None,
    kappa_s_field: torch.Tensor | None = None,
    kappa_b_field: torch.Tensor | None = None,
    frames: int | None = None,
) -> torch.Tensor:
    """Simulate ``T`` frames of the garment (``T − 1`` steps), a differentiable torch operation (:class:`ClothRollout`).

    Args:
        scene: garment, body mesh, boundary, step and settings.
        density: ``ρ``, kg/m³ (0-d tensor or number).
        kappa_s: ``κ_s``, the membrane's factor on the base Young's modulus.
        kappa_b: ``κ_b``, the bending's factor.
        x0: ``[V, 3]`` initial positions, m (not differentiated).
        body: ``[T, B, 3]`` body vertices per frame, m (not differentiated; ``None`` without a body).
        targets: ``[T, D, 3]`` boundary targets per frame, m; frame ``t + 1`` is step ``t``'s target (not
            differentiated; ``None`` without boundary vertices).
        velocity: ``[V, 3]`` initial velocity, m/s (default 0).
        kappa_s_field: ``[F]`` per-face factors on ``κ_s`` (``None``: uniform).
        kappa_b_field: ``[F]`` per-face factors on ``κ_b``; a hinge takes the mean of its two faces'.
        frames: ``T`` where neither ``body`` nor ``targets`` gives it.

    Returns:
        ``[T, V, 3]`` frames, float64, frame 0 being ``x0``.

    Raises:
        ValueError: inconsistent frame counts or shapes, or a step that did not converge.
    """
    dev = backend.torch_device()
    counts = {int(t.shape[0]) for t in (body, targets) if t is not None} | ({frames} if frames is not None else set())
    if len(counts) != 1 or min(counts) < 2:
        raise ValueError(f"body, targets and frames must agree on T >= 2 frames, got {sorted(counts)}; pass frames=T")
    count = counts.pop()
    bodies = int(scene.body_faces.max()) + 1 if scene.body_faces.numel() else 0
    if body is None:
        body = torch.zeros(count, bodies, 3, dtype=F64, device=dev)
    if targets is None:
        targets = torch.zeros(count, scene.boundary_index.numel(), 3, dtype=F64, device=dev)
    if tuple(body.shape[1:]) != (bodies, 3) or tuple(targets.shape[1:]) != (scene.boundary_index.numel(), 3):
        raise ValueError(
            f"body must be [T, {bodies}, 3] and targets [T, {scene.boundary_index.numel()}, 3], "
            f"got {list(body.shape)} and {list(targets.shape)}"
        )
    params = [torch.as_tensor(p, dtype=F64, device=dev) for p in (density, kappa_s, kappa_b)]
    if velocity is None:
        velocity = torch.zeros_like(x0, dtype=F64)
    return ClothRollout.apply(scene, *params, kappa_s_field, kappa_b_field, velocity, x0, body.to(F64), targets.to(F64))


def _control(scene: RolloutScene, body: torch.Tensor, targets: torch.Tensor, t: int, dev) -> ClothControl:
    """Step ``t``'s control: the body from frame ``t`` to ``t + 1``, the boundary at frame ``t + 1``'s targets."""
    return ClothControl(
        body[t].detach().to(dev, F64), body[t + 1].detach().to(dev, F64), scene.boundary_index.to(dev),
        targets[t + 1].detach().to(dev, F64),
    )  # fmt: skip


def _adjoint_solve(solver: SolverCloth, lin: StepLinearisation, load: torch.Tensor) -> torch.Tensor:
    """``λ [V + B, 3]``: ``H λ = load`` on the free vertices, zero elsewhere (``H`` is symmetric: ``Hᵀ = H``)."""
    lam = lin.positions.new_zeros(lin.positions.shape)
    with backend.one_torch_thread_on_cpu():
        solution = solver.linear.solve(lin.matrix, load[lin.free].reshape(-1, 1))
    lam[lin.free] = solution.view(-1, 3)
    return lam


def _explicit_products(solver: SolverCloth, lin: StepLinearisation, lam: torch.Tensor) -> torch.Tensor:
    """``[3]`` ``λ · ∂_θ∇E`` for ``θ = (ρ, κ_s, κ_b)``, the explicit derivatives of ``sensitivity_step``."""
    cfg, parts = solver.config, lin.parts
    zero = torch.zeros_like(lam)
    density = parts.get("inertia", zero)
    if cfg.barrier_stiffness is None:
        density = density + parts.get("contact", zero) + parts.get("friction", zero)
    explicit = (
        density / cfg.density,
        parts.get("membrane", zero) / cfg.kappa_s,
        parts.get("bending", zero) / cfg.kappa_b,
    )
    return torch.stack([(lam * e).sum() for e in explicit])
