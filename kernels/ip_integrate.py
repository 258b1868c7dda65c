"""Integrator-point (IP) integration of the elastic energy, its gradient and its Hessian in the
generalized coordinates q of Q-GMLS (PIE-NeRF §4.4–4.5, Eq. 12–17).

Each IP k carries a cuboid Ω_k with quadrature points h_g and volumes w_kg (Eq. 13). With
F(h) = F_k + ∇F_k·h (Eq. 14) and F = I + Σ_s q_s ⊗ ∇N_s (Eq. 12, 15), the deformation gradient at a
quadrature point is F_kg = I + Σ_s q_s ⊗ D_kgs where D_kgs = ∇N_s(x_k) + ∇²N_s(x_k) h_g is
precomputed once. Then (Eq. 16–17)

    U    = Σ_kg w_kg Ψ(F_kg)
    ∂U/∂q_s,a      = Σ_kg w_kg Σ_b P_ab(F_kg) D_kgs,b
    ∂²U/∂q_s,a∂q_t,f = Σ_kg w_kg Σ_bd D_kgs,b (∂P_ab/∂F_fd) D_kgt,d

Each IP only touches the S shape functions whose kernels cover it, so its Hessian is a dense
[S·3, S·3] block. The material response (SVD, stress, eigen-projected ∂P/∂F) runs in the Warp
kernel of :mod:`kernels.hyperelastic`; the contractions above are matrix products in torch
(cuBLAS/MKL run them near their peak); on CUDA the per-IP blocks are summed into place by a Warp kernel.
On CUDA nothing here reads the device from the host, so an evaluation can be captured in a CUDA graph.
Two assemblies give the same Hessian:

- ``"per_ip"``: one [S, 3G] × [3G, 9S] product per IP, and the blocks summed into the dense
  [3nT, 3nT] Hessian by precomputed block indices. Its work grows with K·S².
- ``"dense"``: D scattered once into all nT shape functions, ``[K·G·3, nT]``, and the sum over
  quadrature points done inside a single [nT, 3KG] × [3KG, 9nT] product, with no per-IP blocks to
  write and sum. Its work grows with K·nT², so it wins when every IP sees most shape functions
  (few, wide kernels: S close to nT), as in interactive bodies of 16 kernels.

``"auto"`` takes the dense one while (nT/S)² stays below :data:`DENSE_ASSEMBLY_RATIO`. Projecting every
quadrature point's ∂P/∂F to PSD makes every IP's Hessian block PSD.

``product_dtype=torch.float32`` forms C and the Hessian's block products (the last equation, both assemblies) in
single precision, from single-precision copies of D made once; everything else stays double: F, the material
response, U, ∂U/∂q, the sums of the per-IP blocks into the Hessian, and the Hessian returned. Against double
products, the Hessian's relative error (Frobenius norm) measured 2.4e-8 to 3.2e-8 with ``"per_ip"`` (each sum over a
block's 3G products is short) and 7e-8 to 2.2e-7 with ``"dense"`` (whose single product sums over all 3KG), on
lattice boxes and beams of 4 to 78 kernels, at rest and bent, PSD-projected or not. Newton's fixed point does not
move (∂U/∂q stays double); its steps may take another iteration. But the Hessian's smallest eigenvalues (the rigid
modes, ~1e-13 of the largest at rest) drown in that error: a static solve, with no mass term to lift them, may meet a
Newton matrix that is no longer positive definite, and a spectral check of the Hessian cannot tell its zero modes.
Double products stay this class's default for that reason; :class:`pienerf.sim.solver.SolverQGMLS` takes single ones for
its dynamic steps on CUDA only, and assembles a Newton matrix that fails to factor again with double ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import warp as wp

from kernels import backend
from kernels.hyperelastic import MaterialModel, material_response

wp.set_module_options({"enable_backward": False})

__all__ = ["DENSE_ASSEMBLY_RATIO", "PRODUCT_DTYPES", "IPIntegral", "IPIntegrator"]

DENSE_ASSEMBLY_RATIO = 3.0
"""``"auto"`` assembly is dense while (nT/S)², the dense product's extra arithmetic, is below this: the per-IP
blocks (K·S²·9 doubles) must be written, gathered and summed, which costs about as much again as their product."""

PRODUCT_DTYPES = (torch.float64, torch.float32)
"""Precisions :class:`IPIntegrator` may form the Hessian's block products in (its ``product_dtype``)."""


@dataclass
class IPIntegral:
    """Result of :meth:`IPIntegrator.evaluate`.

    Attributes:
        energy: total elastic energy U (J), a 0-d tensor.
        ip_energy: energy of each IP ``[K]`` (J).
        min_det: smallest det F over all quadrature points (a 0-d tensor).
        gradient: ∂U/∂q ``[nT, 3]`` (N, or N·m for derivative DOFs), or ``None``.
        hessian: ∂²U/∂q² ``[nT*3, nT*3]``, or ``None``.
    """

    energy: torch.Tensor
    ip_energy: torch.Tensor
    min_det: torch.Tensor
    gradient: torch.Tensor | None = None
    hessian: torch.Tensor | None = None


class IPIntegrator:
    """Precomputed IP quadrature of a Q-GMLS body; evaluates U, ∂U/∂q and ∂²U/∂q² for any q.

    Args:
        index: active shape indices of each IP ``[K, S]`` (int64, −1 where padded).
        shape_grad: D_kgs of the module docstring ``[K, G, S, 3]`` (1/m; zeros where padded).
        weight: quadrature volumes ``[K, G]`` (m³).
        shape_count: number of shape functions nT (the DOFs are ``[nT, 3]``).
        mu: first Lamé parameter per IP ``[K]`` or a scalar (Pa).
        lam: second Lamé parameter per IP ``[K]`` or a scalar (Pa).
        model: the energy density.
        response: the material-point function, :func:`kernels.hyperelastic.material_response` (the
            Warp kernel) unless a reference is swapped in for comparison.
        assembly: ``"dense"``, ``"per_ip"`` or ``"auto"`` (module docstring).
        product_dtype: ``torch.float64`` or ``torch.float32``: the precision of the Hessian's block products
            (module docstring); the Hessian is returned in float64 either way.
    """

    def __init__(
        self,
        index: torch.Tensor,
        shape_grad: torch.Tensor,
        weight: torch.Tensor,
        shape_count: int,
        mu: torch.Tensor | float,
        lam: torch.Tensor | float,
        model: MaterialModel,
        response=material_response,
        assembly: str = "auto",
        product_dtype: torch.dtype = torch.float64,
    ):
        K, G, S, _ = shape_grad.shape
        if index.shape != (K, S) or weight.shape != (K, G):
            raise ValueError(
                f"IPIntegrator: index {tuple(index.shape)}, shape_grad {tuple(shape_grad.shape)} and weight "
                f"{tuple(weight.shape)} disagree; expected [K, S], [K, G, S, 3], [K, G]"
            )
        if assembly not in ("auto", "dense", "per_ip"):
            raise ValueError(f"IPIntegrator: unknown assembly {assembly!r}; use 'auto', 'dense' or 'per_ip'")
        if product_dtype not in PRODUCT_DTYPES:
            raise ValueError(
                f"IPIntegrator: product_dtype {product_dtype!r} is not supported; use torch.float64 or torch.float32"
            )
        if assembly == "auto":
            assembly = "dense" if (shape_count / max(S, 1)) ** 2 < DENSE_ASSEMBLY_RATIO else "per_ip"
        self.assembly = assembly
        self.product_dtype = product_dtype
        self.shape_count = shape_count
        self.model = MaterialModel(model)
        self.response = response
        valid = index >= 0
        self.index = torch.where(valid, index, torch.zeros_like(index))
        self.shape_grad = (shape_grad * valid[:, None, :, None]).to(torch.float64).contiguous()
        self.weight = weight.to(torch.float64)
        self.set_material(mu, lam)
        self.eye = torch.eye(3, dtype=torch.float64, device=shape_grad.device)
        if assembly == "dense":
            # D_kgt,d over all nT shape functions, zero where t does not cover IP k: [K, G, nT, 3]
            dense = torch.zeros(K, G, shape_count, 3, dtype=torch.float64, device=shape_grad.device)
            dense.scatter_add_(2, self.index[:, None, :, None].expand(K, G, S, 3), self.shape_grad)
            self.dense_grad = dense
            # the products' copies of D, made once: [KG, nT, 3] for C and its rows [nT, KG·3]
            self._dense_product = dense.view(K * G, shape_count, 3).to(product_dtype)
            self._dense_rows = self._dense_product.permute(1, 0, 2).reshape(shape_count, K * G * 3).contiguous()
            self._pairs = torch.triu_indices(3, 3, device=shape_grad.device)  # (a, f) with a ≤ f
        else:
            self._prepare_block_sums(valid)

    def _prepare_block_sums(self, valid: torch.Tensor) -> None:
        """Gather order and segment lengths of the ``"per_ip"`` assembly's block sums."""
        shape_count = self.shape_count
        # Block (s, t) of IP k lands at block row index[k, s], column index[k, t]. Assembly is a
        # segmented sum: the contributions of real (unpadded) pairs are gathered in order of their
        # global block, summed per block and written once: atomic scatter-adds of doubles (index_add_) took a
        # third of a step on CUDA (docs/benchmarks.md, the Q-GMLS step).
        block_index = (self.index[:, :, None] * shape_count + self.index[:, None, :]).reshape(-1)
        pair_valid = (valid[:, :, None] & valid[:, None, :]).reshape(-1)
        contribution = torch.nonzero(pair_valid).squeeze(1)
        order = torch.argsort(block_index[contribution], stable=True)
        self._gather = contribution[order]
        self._block, self._block_lengths = torch.unique_consecutive(block_index[self._gather], return_counts=True)
        K, G, S, _ = self.shape_grad.shape
        # the products' copies of D, made once in their precision: D [K, G, S, 3] for C and its rows [K, S, 3G]
        self._shape_grad_product = self.shape_grad.to(self.product_dtype)
        self._shape_grad_rows = self._shape_grad_product.permute(0, 2, 1, 3).reshape(K, S, G * 3).contiguous()
        # the same sums as one Warp launch on CUDA (torch's segment_reduce reads the device from the host, which a
        # CUDA graph forbids), each block's sum written straight to its place in the dense Hessian
        self._block_start = torch.cat([self._block_lengths.new_zeros(1), self._block_lengths.cumsum(0)]).to(torch.int32)
        self._gather32 = self._gather.to(torch.int32)
        self._block32 = self._block.to(torch.int32)

    def set_material(self, mu: torch.Tensor | float, lam: torch.Tensor | float) -> None:
        """Change the Lamé parameters (Pa), per IP ``[K]`` or scalars."""
        K, G = self.weight.shape
        device = self.weight.device
        self.mu = torch.as_tensor(mu, dtype=torch.float64, device=device).expand(K).repeat_interleave(G)
        self.lam = torch.as_tensor(lam, dtype=torch.float64, device=device).expand(K).repeat_interleave(G)

    def deformation_gradient(self, q: torch.Tensor) -> torch.Tensor:
        """F at every quadrature point ``[K, G, 3, 3]`` (Eq. 12 with Eq. 14)."""
        if self.assembly == "dense":
            return self.eye + torch.einsum("ta,kgtb->kgab", q, self.dense_grad)
        return self.eye + torch.einsum("ksa,kgsb->kgab", q[self.index], self.shape_grad)

    def evaluate(
        self, q: torch.Tensor, gradient: bool = True, hessian: bool = True, project: bool = True
    ) -> IPIntegral:
        """Energy, gradient and Hessian at ``q [nT, 3]`` (float64).

        Args:
            q: generalized coordinates ``[nT, 3]``.
            gradient: compute ∂U/∂q.
            hessian: compute ∂²U/∂q² (implies the material Hessian).
            project: clamp each quadrature point's ∂P/∂F at zero (PSD Hessian).
        """
        K, G, S, _ = self.shape_grad.shape
        F = self.deformation_gradient(q)
        derivatives = 2 if hessian else (1 if gradient else 0)
        psi, P, dPdF = self.response(F.reshape(-1, 3, 3), self.mu, self.lam, self.model, project, derivatives)
        ip_energy = (self.weight * psi.view(K, G)).sum(1)
        result = IPIntegral(ip_energy.sum(), ip_energy, _det3(F).min())
        if self.assembly == "dense":
            self._dense_derivatives(result, P, dPdF, gradient, hessian)
            return result
        if gradient or hessian:
            wP = self.weight[..., None, None] * P.view(K, G, 3, 3)
            local = torch.einsum("kgsb,kgab->ksa", self.shape_grad, wP)
            result.gradient = torch.zeros(self.shape_count, 3, dtype=torch.float64, device=q.device)
            result.gradient.index_add_(0, self.index.reshape(-1), local.reshape(-1, 3))
        if hessian:
            wA = (self.weight[..., None, None] * dPdF.view(K, G, 9, 9)).to(self.product_dtype)
            # C_kgt[a, b, f] = Σ_d wA[a, b, f, d] D_kgt,d ; H_k[s, t, a, f] = Σ_gb D_kgs,b C_kgt[a, b, f]
            C = torch.einsum("kgabfd,kgtd->kgbtaf", wA.view(K, G, 3, 3, 3, 3), self._shape_grad_product)
            blocks = torch.bmm(self._shape_grad_rows, C.reshape(K, G * 3, S * 9))
            result.hessian = self.sum_blocks(blocks.reshape(-1, 9))
        return result

    def sum_blocks(self, blocks: torch.Tensor, warp_kernel: bool | None = None) -> torch.Tensor:
        """The dense ``[3nT, 3nT]`` float64 Hessian from the per-IP 3×3 blocks ``[K·S·S, 9]`` (``"per_ip"`` assembly;
        float64 or float32, summed in float64 either way), by the Warp kernel (``warp_kernel``; ``None``: on CUDA)
        or by torch's segmented sum (on the CPU, as fast and already there)."""
        n = self.shape_count
        if blocks.is_cuda if warp_kernel is None else warp_kernel:
            hessian = torch.zeros(3 * n, 3 * n, dtype=torch.float64, device=blocks.device)
            wp.launch(
                _sum_blocks_kernel,
                dim=(self._block32.shape[0], 9),
                inputs=[backend.to_warp(blocks), backend.to_warp(self._gather32), backend.to_warp(self._block_start),
                        backend.to_warp(self._block32), n],
                outputs=[backend.to_warp(hessian)],
                device=backend.warp_device(),
            )
            return hessian
        summed = torch.segment_reduce(blocks[self._gather].to(torch.float64), "sum", lengths=self._block_lengths)
        dense = torch.zeros(n * n, 9, dtype=torch.float64, device=blocks.device)
        dense[self._block] = summed
        return dense.view(n, n, 3, 3).permute(0, 2, 1, 3).reshape(3 * n, 3 * n)

    def _dense_derivatives(self, result: IPIntegral, P, dPdF, gradient: bool, hessian: bool) -> None:
        """Gradient and Hessian of the ``"dense"`` assembly (Eq. 17) from P ``[KG, 3, 3]`` and ∂P/∂F ``[KG, 9, 9]``."""
        K, G, n, _ = self.dense_grad.shape
        D = self.dense_grad.view(K * G, n, 3)
        D_product = self._dense_product
        if gradient or hessian:
            wP = self.weight.reshape(-1, 1, 1) * P  # [KG, a, b]
            result.gradient = torch.einsum("mtb,mab->ta", D, wP)
        if hessian:
            wA = (self.weight.reshape(-1, 1, 1) * dPdF).to(self.product_dtype)
            wA = wA.view(K * G, 3, 3, 3, 3)  # [KG, a, b, f, d]
            # Only the 6 pairs a ≤ f: H is symmetric, so block (f, a) is block (a, f) transposed.
            # C[(kg, b), (p, t)] = Σ_d wA[a_p, b, f_p, d] D_kgt,d ; H_p[s, t] = Σ_(kg, b) D_kgs,b C[(kg, b), (p, t)]
            first, second = self._pairs
            C = torch.einsum("pmbd,mtd->mbpt", wA[:, first, :, second, :], D_product).reshape(K * G * 3, 6 * n)
            H = (self._dense_rows @ C).view(n, 6, n).to(torch.float64)
            full = H.new_empty(n, 3, n, 3)  # [s, a, t, f]
            full[:, second, :, first] = H.permute(1, 2, 0)
            full[:, first, :, second] = H.permute(1, 0, 2)
            result.hessian = full.view(3 * n, 3 * n)

    def assemble_blocks(self, blocks: torch.Tensor, block_index: torch.Tensor) -> torch.Tensor:
        """Sum 3×3 blocks ``[B, 9]`` (row-major a, f) at block positions ``[B]`` (s·nT + t) into a
        dense ``[nT*3, nT*3]`` matrix indexed by (3s + a, 3t + f)."""
        n = self.shape_count
        dense = torch.zeros(n * n, 9, dtype=torch.float64, device=blocks.device)
        dense.index_add_(0, block_index, blocks)
        return dense.view(n, n, 3, 3).permute(0, 2, 1, 3).reshape(3 * n, 3 * n)


@wp.kernel
def _sum_blocks_kernel(
    blocks: wp.array2d(dtype=Any),
    gather: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    block: wp.array(dtype=wp.int32),
    n: int,
    hessian: wp.array2d(dtype=wp.float64),
):
    """Entry ``c`` of global block ``b``: the sum of its contributions ``blocks[gather[start[b]:start[b + 1]], c]``
    (float64 or float32), summed in float64 and written at row 3s + c // 3, column 3t + c % 3 of the Hessian, for the
    block's shape pair s·n + t."""
    b, c = wp.tid()
    total = wp.float64(0.0)
    for j in range(start[b], start[b + 1]):
        total += wp.float64(blocks[gather[j], c])
    s = block[b] // n
    t = block[b] - s * n
    hessian[3 * s + c // 3, 3 * t + c % 3] = total


# Both overloads declared at import, so the module is whole before its first load: a first float32 launch after a
# float64 one (or after a capture) must not rebuild the module under a CUDA graph that holds its kernels.
for _dtype in (wp.float64, wp.float32):
    wp.overload(_sum_blocks_kernel, {"blocks": wp.array2d(dtype=_dtype)})


def _det3(F: torch.Tensor) -> torch.Tensor:
    """det of 3×3 matrices ``[..., 3, 3]`` by cofactors: elementwise, so no LU factorisation, no library handle and
    nothing a CUDA graph capture forbids."""
    return (F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
            - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
            + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]))
