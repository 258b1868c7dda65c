"""cuSOLVER's batched Jacobi eigensolver: input checks everywhere; decompositions where it and a GPU are present."""

from __future__ import annotations

import pytest
import torch

from kernels import cusolver, element_terms

needs_cusolver = pytest.mark.skipif(not cusolver.available(), reason="needs cuSOLVER and a CUDA device")


def _symmetric(count: int, n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """Random symmetric matrices, a third of them scaled by 1e8 (stiff contacts beside soft cloth)."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(count, n, n, generator=g, dtype=torch.float64)
    a = a + a.transpose(1, 2)
    a[: count // 3] *= 1e8
    return a.to(dtype)


def test_refuses_what_it_cannot_decompose():
    with pytest.raises(ValueError, match=r"\[N, n, n\]"):
        cusolver.eigh(torch.zeros(4, 3))
    with pytest.raises(ValueError, match="CUDA device"):
        cusolver.eigh(torch.zeros(2, 3, 3))


def test_unavailable_library_names_the_fix():
    if cusolver.available():
        pytest.skip("cuSOLVER is present here")
    if not torch.cuda.is_available():
        assert not cusolver.available()
        return
    with pytest.raises(cusolver.CusolverError, match="CUSOLVER_LIBRARY"):
        cusolver.eigh(torch.zeros(2, 3, 3, device="cuda"))


@needs_cusolver
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n", [9, 12, 32])
def test_decompositions_match_lapack(dtype, n):
    """Eigenvalues as LAPACK's (ascending), orthonormal eigenvectors, ``Q Λ Qᵀ`` the input; info all zero."""
    h = _symmetric(600, n, dtype)
    values, vectors, info = cusolver.eigh(h.cuda())
    values, vectors = values.cpu().double(), vectors.cpu().double()
    assert int(info.count_nonzero()) == 0
    expected = torch.linalg.eigvalsh(h.double())
    scale = h.double().abs().amax((1, 2), keepdim=True)
    tol = 1e-12 if dtype == torch.float64 else 5e-5
    assert ((values - expected).abs() / scale[:, :, 0]).max() < tol
    eye = torch.eye(n, dtype=torch.float64).expand_as(vectors)
    assert (vectors.transpose(1, 2) @ vectors - eye).abs().max() < 10 * tol
    rebuilt = (vectors * values[:, None, :]) @ vectors.transpose(1, 2)
    assert ((rebuilt - h.double()).abs() / scale).max() < 10 * tol


@needs_cusolver
def test_psd_projection_on_cuda_matches_the_cpu_one():
    """``project_psd`` takes cuSOLVER's path on CUDA and LAPACK's on the CPU: the same filtered matrices, an empty
    batch included."""
    h = _symmetric(300, 12, torch.float64, seed=1)
    for absolute in (False, True):
        on_gpu = element_terms.project_psd(h.cuda(), absolute).cpu()
        on_cpu = element_terms.project_psd(h, absolute)
        scale = h.abs().amax((1, 2), keepdim=True)
        assert ((on_gpu - on_cpu).abs() / scale).max() < 1e-12
    assert element_terms.project_psd(h[:0].cuda()).shape == (0, 12, 12)
