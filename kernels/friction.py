"""IPC's smoothed lagged friction potential, its gradient and Hessian, one Warp thread per contact.

The garment simulator (PhysAvatar §3.2 with Codim-IPC) adds the lagged friction potential of IPC (Li et al. 2020,
§5, Eq. 14–16) to its incremental potential and evaluates it at every Newton iteration and line-search trial.
For contact ``k`` with lagged closest-point weights ``w_ki`` over its four vertices, lagged tangent projector
``P_k = I − n_k n_kᵀ`` and lagged normal-force magnitude times friction coefficient ``μλ_k``:

* ``u_k = P_k Σ_i w_ki Δx_i`` is the tangential relative displacement since the start of the step, m;
  ``y = ‖u_k‖``.
* ``D_k = μλ_k f₀(y)`` with ``f₀(y) = −y³/(3ε²) + y²/ε + ε/3`` for ``y < ε`` and ``f₀(y) = y`` above, where
  ``ε = ε_v Δt`` (m) is the velocity threshold times the step; ``f₀`` is C¹ at ``ε``.
* ``∂D_k/∂x_i = w_ki μλ_k (f₁/y) u_k`` with ``f₁/y = 2/ε − y/ε²`` below ``ε`` and ``1/y`` above.
* Hessian blocks ``∂²D_k/∂x_i∂x_j = w_ki w_kj μλ_k ((f₁/y) P_k + c u_k u_kᵀ)`` with ``c = −1/(ε² y)`` below
  ``ε``, ``−1/y³`` above and ``c = 0`` at ``y = 0`` exactly (where ``u_k = 0``), so no entry is ever NaN or
  infinite. For a symmetric idempotent ``P_k`` this is the exact Hessian; it is positive semi-definite.

Units: displacements and ``ε`` in m, ``μλ`` in N; energies in J, gradients in N, Hessians in N/m. Everything is
float64, as in the simulator (1 mm contact gaps on 1 m coordinates). The math and outputs match the reference
:func:`kernels.reference.friction.friction_potential`, a chain of ~20 torch operations whose cost on a GPU is
mostly launch overhead; here it is one launch on torch's current stream (:mod:`kernels.backend`).

Warp, not Taichi: the simulator around it is Warp and torch, and the kernel is a per-contact map with no reduction.
Measured on this project's 2-core CPU (Warp on one thread against the torch version on one thread, as the simulator
runs it), with Hessians: K = 1 000 contacts 0.11 ms against 0.55 ms, K = 20 000 2.0 ms against 33 ms; without:
0.07 ms against 0.18 ms, 0.59 ms against 3.2 ms. Not yet measured on a GPU.
"""

import math

import torch
import warp as wp

from kernels import backend

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False})

__all__ = ["friction_potential"]

_MAT33D = wp.types.matrix((3, 3), wp.float64)


@wp.kernel
def _friction_kernel(
    displacement: wp.array(dtype=wp.vec3d),
    index: wp.array2d(dtype=wp.int32),
    weight: wp.array2d(dtype=wp.float64),
    projector: wp.array(dtype=_MAT33D),
    force: wp.array(dtype=wp.float64),
    eps: wp.float64,
    with_hessian: wp.int32,
    energy: wp.array(dtype=wp.float64),
    grad: wp.array2d(dtype=wp.vec3d),
    hess: wp.array3d(dtype=wp.float64),
):
    k = wp.tid()
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    gap = wp.vec3d(zero, zero, zero)
    for i in range(4):
        gap += weight[k, i] * displacement[index[k, i]]
    p = projector[k]
    u = p * gap
    y = wp.length(u)
    inv_eps = one / eps
    f0 = y
    f1_over_y = zero
    c = zero
    if y < eps:
        f0 = -(y * y * y) * (inv_eps * inv_eps) / wp.float64(3.0) + y * y * inv_eps + eps / wp.float64(3.0)
        f1_over_y = wp.float64(2.0) * inv_eps - y * (inv_eps * inv_eps)
        if y > zero:
            c = -(inv_eps * inv_eps) / y
    else:
        f1_over_y = one / y
        c = -one / (y * y * y)
    mu_lambda = force[k]
    energy[k] = mu_lambda * f0
    scaled_u = u * (mu_lambda * f1_over_y)
    for i in range(4):
        grad[k, i] = scaled_u * weight[k, i]
    if with_hessian != 0:
        block = (p * f1_over_y + wp.outer(u, u) * c) * mu_lambda
        for i in range(4):
            for j in range(4):
                wij = weight[k, i] * weight[k, j]
                for a in range(3):
                    for b in range(3):
                        hess[k, 3 * i + a, 3 * j + b] = wij * block[a, b]


def friction_potential(
    displacement: torch.Tensor,
    index: torch.Tensor,
    weight: torch.Tensor,
    projector: torch.Tensor,
    force: torch.Tensor,
    eps: float,
    hessian: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Per-contact lagged friction energy ``μλ f₀(‖u‖)`` with gradient and, optionally, Hessian (IPC Eq. 14–16).

    Args:
        displacement: ``[N, 3]`` float64 displacement of every vertex since the start of the step, m.
        index: ``[K, 4]`` int32 or int64 vertex indices of each contact, each in ``[0, N)`` (not checked: an index
            out of range reads unrelated memory).
        weight: ``[K, 4]`` float64 closest-point weights: ``Σ_i w_i x_i`` is the contact's gap vector, 1.
        projector: ``[K, 3, 3]`` float64 lagged tangent projectors ``I − n nᵀ``, 1.
        force: ``[K]`` float64 lagged ``μλ``: friction coefficient times normal-force magnitude, N.
        eps: ``ε = ε_v Δt``, the displacement below which static friction is smoothed, m; positive.
        hessian: also compute the ``[K, 12, 12]`` Hessians; ``False`` skips computing and storing them.

    Returns:
        ``(energy [K] (J), grad [K, 4, 3] (N), hess [K, 12, 12] (N/m) or None)``; Hessian rows and columns are
        ordered vertex-major (``3 * vertex + axis``). All on the device of the inputs, float64.

    Raises:
        ValueError: an argument has the wrong shape, dtype or device, or ``eps`` is not a positive finite number.
    """
    _check_float64(displacement, (None, 3), "displacement", "[N, 3]")
    if index.dtype not in (torch.int32, torch.int64) or index.dim() != 2 or index.shape[1] != 4:
        raise ValueError(
            f"index must be an int32 or int64 [K, 4] tensor, got {index.dtype} {list(index.shape)}; "
            "stack each contact's four vertex ids into one row"
        )
    k = index.shape[0]
    _check_float64(weight, (k, 4), "weight", "[K, 4]")
    _check_float64(projector, (k, 3, 3), "projector", "[K, 3, 3]")
    _check_float64(force, (k,), "force", "[K]")
    for name, t in (("index", index), ("weight", weight), ("projector", projector), ("force", force)):
        if t.device != displacement.device:
            raise ValueError(
                f"{name} is on {t.device} but displacement is on {displacement.device}; move it with "
                f".to('{displacement.device}')"
            )
    if not (math.isfinite(eps) and eps > 0.0):
        raise ValueError(f"eps ({eps}) must be a positive finite length ε_v Δt, m")

    device = displacement.device
    energy = torch.empty(k, dtype=torch.float64, device=device)
    grad = torch.empty(k, 4, 3, dtype=torch.float64, device=device)
    hess = torch.empty(k if hessian else 0, 12, 12, dtype=torch.float64, device=device)
    if k:
        wp.launch(
            _friction_kernel,
            dim=k,
            inputs=[
                backend.warp_arg(displacement.contiguous(), dtype=wp.vec3d),
                backend.warp_arg(index.to(torch.int32).contiguous()),
                backend.warp_arg(weight.contiguous()),
                backend.warp_arg(projector.contiguous(), dtype=_MAT33D),
                backend.warp_arg(force.contiguous()),
                wp.float64(eps),
                1 if hessian else 0,
            ],
            outputs=[
                backend.warp_arg(energy),
                backend.warp_arg(grad, dtype=wp.vec3d),
                backend.warp_arg(hess),
            ],
            device=backend.warp_device(),
        )
    return energy, grad, hess if hessian else None


def _check_float64(t: torch.Tensor, shape: tuple, name: str, layout: str) -> None:
    """Raise unless ``t`` is a float64 tensor of ``shape`` (a ``None`` entry matches any size)."""
    if t.dtype != torch.float64:
        raise ValueError(f"{name} must be a float64 {layout} tensor, got {t.dtype}; convert with .to(torch.float64)")
    if t.dim() != len(shape) or any(want is not None and got != want for got, want in zip(t.shape, shape, strict=True)):
        expected = ["N" if want is None else want for want in shape]
        raise ValueError(f"{name} must have shape {layout}, here {expected}, got {list(t.shape)}")
