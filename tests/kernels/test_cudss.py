"""cuDSS binding: block-to-CSR conversion everywhere; factor and solve where cuDSS and a GPU are present."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch

from kernels import cudss


def _random_blocks(n: int, pairs: int, seed: int = 0):
    """Duplicated, unsorted 3×3 COO blocks of a symmetric, diagonally dominant (SPD) matrix."""
    g = torch.Generator().manual_seed(seed)
    r = torch.randint(0, n, (pairs,), generator=g)
    c = torch.randint(0, n, (pairs,), generator=g)
    b = torch.randn(pairs, 3, 3, generator=g, dtype=torch.float64)
    rows = torch.cat([r, c, torch.arange(n), torch.arange(n)])
    cols = torch.cat([c, r, torch.arange(n), torch.arange(n)])
    diag = (2.0 * pairs / n + 5.0) * 6.0 * torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
    blocks = torch.cat([b, b.transpose(1, 2), diag, 0.5 * diag])
    order = torch.randperm(rows.numel(), generator=g)
    return rows[order], cols[order], blocks[order]


def _dense(rows, cols, blocks, n):
    a = np.zeros((3 * n, 3 * n))
    for r, c, b in zip(rows.tolist(), cols.tolist(), blocks.numpy(), strict=True):
        a[3 * r : 3 * r + 3, 3 * c : 3 * c + 3] += b
    return a


def test_blocks_to_csr_matches_the_dense_sum_and_is_sorted():
    n = 17
    rows, cols, blocks = _random_blocks(n, 40)
    crow, col, values = cudss.blocks_to_csr(rows, cols, blocks, n)
    assert crow.shape == (3 * n + 1,) and int(crow[-1]) == col.numel() == values.numel()
    m = scipy.sparse.csr_matrix((values.numpy(), col.numpy(), crow.numpy()), shape=(3 * n, 3 * n))
    assert m.has_sorted_indices
    m.sum_duplicates()
    assert m.nnz == col.numel(), "each (row, column) is stored once"
    np.testing.assert_allclose(m.toarray(), _dense(rows, cols, blocks, n), rtol=0, atol=1e-12)


def test_blocks_to_csr_keeps_empty_block_rows():
    rows, cols = torch.tensor([0, 3]), torch.tensor([0, 3])
    scale = torch.tensor([2.0, 5.0], dtype=torch.float64)
    blocks = torch.eye(3, dtype=torch.float64).expand(2, 3, 3) * scale[:, None, None]
    crow, col, values = cudss.blocks_to_csr(rows, cols, blocks, 4)
    m = scipy.sparse.csr_matrix((values.numpy(), col.numpy(), crow.numpy()), shape=(12, 12)).toarray()
    np.testing.assert_array_equal(np.diag(m), [2, 2, 2, 0, 0, 0, 0, 0, 0, 5, 5, 5])


def test_solver_refuses_a_cpu_device():
    with pytest.raises(ValueError, match="CUDA device"):
        cudss.SparseSPDSolver("cpu")


def test_unavailable_library_names_the_fix(monkeypatch):
    if cudss.available():
        pytest.skip("cuDSS is present here")
    with pytest.raises(cudss.CudssError, match="pip install nvidia-cudss"):
        cudss.version()


@pytest.mark.skipif(not cudss.available(), reason="needs cuDSS and a CUDA device")
def test_factor_and_solve_match_a_dense_solve_and_reuse_the_analysis():
    n = 60
    rows, cols, blocks = _random_blocks(n, 200, seed=1)
    a = torch.from_numpy(_dense(rows, cols, blocks, n))
    solver = cudss.SparseSPDSolver("cuda")
    crow, col, values = (t.cuda() for t in cudss.blocks_to_csr(rows, cols, blocks, n))
    assert solver.factor(crow, col, values)
    rhs = torch.randn(3 * n, 2, dtype=torch.float64)
    x = solver.solve(rhs.cuda()).cpu()
    torch.testing.assert_close(x, torch.linalg.solve(a, rhs), rtol=1e-10, atol=1e-12)
    # same pattern, new values: no new analysis
    assert solver.factor(crow, col, 2.0 * values)
    x1 = solver.solve(rhs[:, 0].cuda()).cpu()
    torch.testing.assert_close(x1, torch.linalg.solve(2.0 * a, rhs[:, 0]), rtol=1e-10, atol=1e-12)
    assert (solver.analyses, solver.factorizations) == (1, 2)
    # queued: the solve runs behind the factorisation and the status is read afterwards
    solver.queue_factor(crow, col, 3.0 * values)
    x3 = solver.solve(rhs.cuda()).cpu()
    assert solver.positive_definite()
    torch.testing.assert_close(x3, torch.linalg.solve(3.0 * a, rhs), rtol=1e-10, atol=1e-12)
    solver.queue_factor(crow, col, -values)
    assert not solver.positive_definite()
    # an indefinite matrix is reported, not factored silently
    assert not solver.factor(crow, col, -values)
