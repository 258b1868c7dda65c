"""Per-element energy terms of the garment simulator's kernels, and what its kernel modules share.

The energy kernels of :mod:`kernels.shell` (StVK membrane, discrete-shell bending) and :mod:`kernels.contact` (the IPC
barrier over contact pairs) return, per element, the energy, its gradient and its dense Hessian
(:class:`ElementTerms`), which the implicit Newton solver of the garment simulator (PhysAvatar §3.2, Appendix A.3)
filters with :func:`project_psd` and scatters into a sparse matrix. This module also holds what those modules and
:mod:`kernels.ipc_barrier`, :mod:`kernels.ccd` and :mod:`kernels.friction` share: the Warp building blocks they write
dense element matrices with, their argument checks and launch plumbing, and the float64 overload declaration each
runs at import (:func:`declare_float64_overloads`).

Conventions:

* Every per-element Hessian is exact (closed form, no Gauss-Newton truncation); :func:`project_psd` replaces it
  by its nearest positive semi-definite matrix (eigenvalues clamped at zero). The projection runs after the
  kernel as one batched eigen-decomposition: cuSOLVER's batched Jacobi solver on CUDA (:mod:`kernels.cusolver`,
  faster than ``torch.linalg.eigh`` there, and it does not wait for the device), ``torch.linalg.eigh``
  (LAPACK) on the CPU. The projection costs several times the kernel (``docs/benchmarks.md``); a per-thread
  Jacobi eigensolver in Warp is slower on both devices (:mod:`kernels.assembly`); the solver skips projection
  where the Hessian is known PSD (barrier pairs far from contact have zero Hessians).
* Kernels are generic over the scalar type: ``x`` in float32 runs float32 kernels (the default, for GPU
  speed), ``x`` in float64 runs the same kernels in float64 (used by the tests for closed-form checks, and by
  callers that want contact distances of 1 mm resolved on coordinates of 1 m: float32 keeps about 1e-7 m).
* Hessian rows and columns are ordered vertex-major (``3 * vertex + axis``).
"""

import math
from typing import Any, NamedTuple

import torch
import warp as wp

from kernels import backend, cusolver

# Every derivative in the kernels that use these functions is written out in closed form; Warp's adjoint code would
# only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = [
    "ElementTerms",
    "add_block",
    "add_vec",
    "allocate_terms",
    "check_index",
    "check_positions",
    "check_values",
    "declare_float64_overloads",
    "launch_rows",
    "matrix_block",
    "per_element",
    "project_psd",
    "scalar_type",
    "store_terms",
    "vec3_array",
]


class ElementTerms(NamedTuple):
    """Per-element energy, gradient and Hessian.

    Attributes:
        energy: ``[N]`` energy of each element, J.
        grad: ``[N, k, 3]`` gradient with respect to the element's ``k`` vertices, N (J/m).
        hess: ``[N, 3k, 3k]`` Hessian, N/m, rows and columns ordered vertex-major (``3 * vertex + axis``).
    """

    energy: torch.Tensor
    grad: torch.Tensor
    hess: torch.Tensor


# matrices per batched eigen-decomposition: float64 12×12 batches of 10⁵ raised CUSOLVER_STATUS_INTERNAL_ERROR on an
# H100 (the ~10⁵ hinges of a 224² sheet), so larger batches are split
_EIGH_BATCH = 1 << 15


def project_psd(hess: torch.Tensor, absolute: bool = False, eigen_dtype: torch.dtype | None = None) -> torch.Tensor:
    """Positive semi-definite stand-ins for a batch of symmetric matrices.

    Args:
        hess: ``[N, n, n]`` symmetric matrices.
        absolute: flip negative eigenvalues instead of clamping them (Chen et al. 2024, "Stabler Neo-Hookean
            simulation: absolute eigenvalue filtering for projected Newton"): the Newton direction then keeps
            the curvature of buckling modes instead of treating them as flat, which takes projected Newton to
            convergence in fewer iterations on compressed cloth.
        eigen_dtype: decompose copies of the matrices in this dtype (e.g. float32 ones of float64 matrices, which
            cuSOLVER's batched Jacobi decomposes in about two thirds of the time); the result is rebuilt in
            ``hess``'s dtype. ``Q max(Λ, 0) Qᵀ`` is PSD for any ``Q``, so the rounding moves the filtered matrix by
            about the decomposition's precision but never makes it indefinite. ``None``: ``hess``'s dtype.

    Returns:
        ``[N, n, n]``: ``Q max(Λ, 0) Qᵀ`` of each eigen-decomposition ``Q Λ Qᵀ`` (the nearest PSD matrix in the
        Frobenius norm), or ``Q |Λ| Qᵀ`` with ``absolute``. The decompositions are cuSOLVER's batched Jacobi
        (:func:`kernels.cusolver.eigh`) on CUDA where it loads, ``torch.linalg.eigh`` elsewhere.
    """
    if hess.shape[0] > _EIGH_BATCH:  # cuSOLVER's batched eigensolver fails on very large batches
        return torch.cat([project_psd(part, absolute, eigen_dtype) for part in hess.split(_EIGH_BATCH)])
    if hess.shape[0] == 0:
        return hess.clone()
    decomposed = hess if eigen_dtype is None else hess.to(eigen_dtype)
    if hess.device.type == "cuda" and hess.shape[-1] <= cusolver.MAX_SIZE and cusolver.available():
        eigval, eigvec, _ = cusolver.eigh(decomposed)  # batched Jacobi: no read from the device
    else:
        eigval, eigvec = torch.linalg.eigh(decomposed)
    eigval, eigvec = eigval.to(hess.dtype), eigvec.to(hess.dtype)
    eigval = eigval.abs() if absolute else eigval.clamp_min(0.0)
    return (eigvec * eigval.unsqueeze(-2)) @ eigvec.transpose(-1, -2)


# ---------------------------------------------------------------------------------------------------------------
# Warp building blocks of dense element matrices
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def add_block(h: Any, row: int, col: int, m: Any):
    """``h[3 row : 3 row + 3, 3 col : 3 col + 3] += m`` for a square matrix ``h``."""
    for i in range(3):
        for j in range(3):
            h[3 * row + i, 3 * col + j] = h[3 * row + i, 3 * col + j] + m[i, j]
    return h


@wp.func
def matrix_block(h: Any, row: int, col: int):
    """The 3×3 block ``h[3 row : 3 row + 3, 3 col : 3 col + 3]``."""
    return wp.matrix_from_rows(
        wp.vector(h[3 * row, 3 * col], h[3 * row, 3 * col + 1], h[3 * row, 3 * col + 2]),
        wp.vector(h[3 * row + 1, 3 * col], h[3 * row + 1, 3 * col + 1], h[3 * row + 1, 3 * col + 2]),
        wp.vector(h[3 * row + 2, 3 * col], h[3 * row + 2, 3 * col + 1], h[3 * row + 2, 3 * col + 2]),
    )


@wp.func
def add_vec(g: Any, k: int, v: Any):
    """``g[3k : 3k + 3] += v`` for a flat vector ``g``."""
    for i in range(3):
        g[3 * k + i] = g[3 * k + i] + v[i]
    return g


@wp.func
def store_terms(energy: Any, grad: Any, hess: Any, i: int, e: Any, g: Any, h: Any, nv: int):
    """Write one element's energy, ``[nv, 3]`` gradient and ``[3 nv, 3 nv]`` Hessian to row ``i``."""
    energy[i] = e
    for a in range(3 * nv):
        grad[i, a // 3, a % 3] = g[a]
        for b in range(3 * nv):
            hess[i, a, b] = h[a, b]


# ---------------------------------------------------------------------------------------------------------------
# Argument checks and launches
# ---------------------------------------------------------------------------------------------------------------


def scalar_type(x: torch.Tensor):
    """Warp's scalar type of ``x``'s dtype: ``wp.float64`` for float64, else ``wp.float32``."""
    return wp.float64 if x.dtype == torch.float64 else wp.float32


def vec3_array(x: torch.Tensor) -> tuple:
    """``x [N, 3]`` as a :func:`kernels.backend.launch` argument: an array of 3-vectors."""
    return x, wp.vec3d if x.dtype == torch.float64 else wp.vec3f


def check_positions(x: torch.Tensor) -> None:
    """Raise ``ValueError`` unless ``x`` is a contiguous float32 or float64 ``[V, 3]`` tensor of positions."""
    if x.dtype not in (torch.float32, torch.float64) or x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"positions must be a float32 or float64 [V, 3] tensor, got {x.dtype} {tuple(x.shape)}")
    if not x.is_contiguous():
        raise ValueError("positions are not contiguous; call .contiguous() first")


def check_index(index: torch.Tensor, width: int, what: str) -> None:
    """Raise ``ValueError`` (naming ``what``) unless ``index`` is a contiguous int32 ``[N, width]`` tensor."""
    if index.dtype != torch.int32 or index.dim() != 2 or index.shape[1] != width:
        raise ValueError(
            f"{what} must be an int32 [N, {width}] tensor, got {index.dtype} {tuple(index.shape)}; "
            f"convert with .to(torch.int32)"
        )
    if not index.is_contiguous():
        raise ValueError(f"{what} is not contiguous; call .contiguous() first")


def check_values(t: torch.Tensor, x: torch.Tensor, shape: tuple, what: str) -> torch.Tensor:
    """``t`` made contiguous, after checking its shape and that its dtype is ``x``'s (``ValueError``, naming
    ``what``, if not)."""
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"{what} must have shape {list(shape)}, got {list(t.shape)}")
    if t.dtype != x.dtype:
        raise ValueError(f"{what} is {t.dtype} but positions are {x.dtype}; convert with .to({x.dtype})")
    return t.contiguous()


def per_element(value, x: torch.Tensor, n: int, what: str) -> torch.Tensor:
    """A per-element parameter as an ``[n]`` tensor in ``x``'s dtype: checked as :func:`check_values` if a tensor,
    else a finite non-negative scalar broadcast to all ``n`` elements."""
    if isinstance(value, torch.Tensor):
        return check_values(value, x, (n,), what)
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{what} ({value}) must be a finite non-negative number")
    return torch.full((n,), float(value), dtype=x.dtype, device=x.device)


def launch_rows(kernel, n: int, inputs: list, outputs: list) -> None:
    """Launch ``kernel`` over ``n`` rows with ``inputs`` then ``outputs`` as its arguments; nothing when ``n`` is 0."""
    if n:
        backend.launch(kernel, n, [*inputs, *outputs])


def allocate_terms(x: torch.Tensor, n: int, nv: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Uninitialised ``(energy [n], grad [n, nv, 3], hess [n, 3 nv, 3 nv])`` in ``x``'s dtype and device, for the
    :class:`ElementTerms` of ``n`` elements of ``nv`` vertices."""
    return (
        torch.empty(n, dtype=x.dtype, device=x.device),
        torch.empty(n, nv, 3, dtype=x.dtype, device=x.device),
        torch.empty(n, 3 * nv, 3 * nv, dtype=x.dtype, device=x.device),
    )


# ---------------------------------------------------------------------------------------------------------------
# Overloads declared before a module is built
# ---------------------------------------------------------------------------------------------------------------


# the concrete dtypes of the generic array arguments that are not float64 scalars, by argument name
_ARRAY_DTYPES = {"x": wp.vec3d, "dx": wp.vec3d, "rest_inv": wp.mat22d}


def declare_float64_overloads(namespace: dict[str, Any]) -> None:
    """Declare the float64 overload (positions ``vec3d``) of every generic kernel in ``namespace`` now.

    Each kernel module of the garment simulator calls it with its own ``globals()`` at the end of its import. Warp
    builds a module with the overloads its generic kernels have when it is first loaded; an overload that a later
    launch instantiates rebuilds the whole module. Left to the launches, the garment solver rebuilt its kernels'
    module at its first steps and again at its first contact, for the barrier kernels, a long stall in the middle
    of a simulation (``docs/benchmarks.md``); declared at import, the first launch of a module builds them all at
    once. Other dtypes still work, at the cost of a rebuild.

    Args:
        namespace: a kernel module's ``globals()``; the generic ``wp.Kernel`` values it defines get the overload.
    """
    name = namespace["__name__"]
    for kernel in [
        value
        for value in namespace.values()
        if isinstance(value, wp.Kernel) and value.is_generic and value.func.__module__ == name
    ]:
        types = {}
        for arg in kernel.adj.args:
            if arg.type is Any:
                types[arg.label] = wp.float64
            elif wp.types.is_array(arg.type) and arg.type.dtype is Any:
                types[arg.label] = wp.array(dtype=_ARRAY_DTYPES.get(arg.label, wp.float64), ndim=arg.type.ndim)
        wp.overload(kernel, types)
