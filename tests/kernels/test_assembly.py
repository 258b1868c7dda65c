"""Block-sparse assembly of element Hessians against the dense torch reference."""

import pytest
import torch

from kernels import assembly
from kernels.reference import assembly as reference

F64 = torch.float64


def _matrices(g: torch.Generator, count: int, size: int) -> torch.Tensor:
    """Random matrices, not symmetric: a transposed block would show."""
    return torch.randn(count, size, size, generator=g, dtype=F64)


def _problem(device, seed: int = 0, vertices: int = 40, kinematic: int = 8):
    """Random triangles and quads over vertices of which some are kinematic, with random Hessians."""
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(vertices, generator=g)
    dof = torch.full((vertices,), -1, dtype=torch.int32)
    dof[order[kinematic:]] = torch.arange(vertices - kinematic, dtype=torch.int32)
    elements = []
    for k, count in ((3, 30), (4, 25)):
        index = torch.stack([torch.randperm(vertices, generator=g)[:k] for _ in range(count)]).to(torch.int32)
        elements.append([index, _matrices(g, count, 3 * k)])
    p_kin = torch.randn(vertices, 3, generator=g, dtype=F64)
    to = lambda t: t.to(device).contiguous()  # noqa: E731
    return to(dof), to(p_kin), [[to(i), to(h)] for i, h in elements], vertices - kinematic


def _assemble(pattern, elements, dof, p_kin, scale=0.5):
    values = torch.zeros(pattern.col.numel(), dtype=F64, device=dof.device)
    rhs = torch.zeros(pattern.n, 3, dtype=F64, device=dof.device)
    missing = torch.zeros(1, dtype=torch.int32, device=dof.device)
    for index, hess in elements:
        assembly.scatter_hessians(pattern, values, rhs, missing, index, hess, dof, p_kin, scale)
    return values, rhs, int(missing)


def _dense(pattern, values) -> torch.Tensor:
    """The dense matrix of CSR ``values`` on ``pattern``."""
    size = 3 * pattern.n
    crow = pattern.crow.long()
    rows = torch.repeat_interleave(torch.arange(size, device=crow.device), crow[1:] - crow[:-1])
    dense = torch.zeros(size, size, dtype=values.dtype, device=values.device)
    dense[rows, pattern.col.long()] = values
    return dense


def test_scatter_matches_the_dense_reference(device):
    dof, p_kin, elements, n = _problem(device)
    keys = torch.cat([assembly.block_keys(index, dof, n) for index, _ in elements])
    pattern = assembly.block_pattern(keys, n)
    values, rhs, missing = _assemble(pattern, elements, dof, p_kin)
    expected, expected_rhs = reference.newton_matrix(n, [(index, hess, 0.5) for index, hess in elements], dof, p_kin)
    assert missing == 0
    # Each entry is a sum of c terms, added atomically (on CUDA in an order no run repeats) against the reference's
    # element order: they differ by at most 2 c eps sum|term|, plus the roundings of the scale and of the pushes'
    # 3-term products. Counting and magnitudes come from the reference itself, on ones and on absolute values.
    magnitude, magnitude_rhs = reference.newton_matrix(
        n, [(index, hess.abs(), 0.5) for index, hess in elements], dof, p_kin.abs()
    )
    count, count_rhs = reference.newton_matrix(
        n, [(index, torch.ones_like(hess), 0.5) for index, hess in elements], dof, torch.ones_like(p_kin)
    )
    eps = torch.finfo(torch.float64).eps
    for got, want, terms, size in (
        (_dense(pattern, values), expected, 2 * count, magnitude),
        (rhs, expected_rhs, 2 * count_rhs.abs(), magnitude_rhs.abs()),  # the reference pushes with a minus sign
    ):
        bound = (2 * terms + 4) * eps * size
        assert bool(((got - want).abs() <= bound).all()), float(((got - want).abs() - bound).max())
    assert bool((count > 0).any()) and bool((count_rhs.abs() > 0).any())


def test_missing_blocks_are_counted_and_bounded_on_the_diagonal(device):
    """A block the pattern lacks adds its Frobenius norm to its row's diagonal instead: the other entries are exact,
    and the matrix exceeds the exact one by a PSD matrix (symmetric PSD element Hessians)."""
    dof, p_kin, elements, n = _problem(device, seed=2)
    elements = [[index, hess @ hess.transpose(1, 2)] for index, hess in elements]  # symmetric PSD
    (tri_index, _), (quad_index, quad_hess) = elements
    pattern = assembly.block_pattern(assembly.block_keys(tri_index, dof, n), n)  # the quads' blocks partly absent
    known = set(pattern.keys().tolist())
    bound = torch.zeros(n, dtype=F64)
    absent = 0
    for index, hess in zip(quad_index.tolist(), quad_hess.cpu(), strict=True):
        for a, va in enumerate(index):
            for b, vb in enumerate(index):
                row, col = int(dof[va]), int(dof[vb])
                if row >= 0 and col >= 0 and row * n + col not in known:
                    absent += 1
                    bound[row] += 0.5 * hess[3 * a : 3 * a + 3, 3 * b : 3 * b + 3].norm()
    assert absent > 0
    values, _, missing = _assemble(pattern, elements, dof, p_kin)
    assert missing == absent
    dense = _dense(pattern, values)
    expected, _ = reference.newton_matrix(n, [(i, h, 0.5) for i, h in elements], dof, p_kin)
    present = _dense(pattern, torch.ones_like(values)) != 0
    diagonal = torch.eye(3 * n, dtype=torch.bool, device=device)
    tol = 1e-12 * expected.abs().max()
    torch.testing.assert_close(dense[present & ~diagonal], expected[present & ~diagonal], rtol=0, atol=tol)
    torch.testing.assert_close(
        dense.diagonal() - expected.diagonal(), bound.repeat_interleave(3).to(device), rtol=0, atol=tol
    )
    assert float(torch.linalg.eigvalsh(dense - expected).min()) > -tol
    grown = assembly.block_pattern(torch.cat([pattern.keys(), assembly.block_keys(quad_index, dof, n)]), n)
    full, _, missing = _assemble(grown, elements, dof, p_kin)
    assert missing == 0 and full.numel() > values.numel()


def test_block_pattern_holds_every_diagonal_block_and_marks_it(device):
    """Keys with repeats and without some diagonal blocks: the pattern has each block once, every diagonal block,
    and ``diagonal`` addresses exactly the diagonal blocks' entries, in order."""
    g = torch.Generator().manual_seed(4)
    n = 12
    keys = torch.randint(0, n * n, (40,), generator=g).to(device)
    pattern = assembly.block_pattern(torch.cat([keys, keys[:10]]), n)
    expected = torch.unique(torch.cat([keys, torch.arange(n, device=device) * (n + 1)]))
    assert torch.equal(pattern.keys(), expected)
    values = torch.zeros(pattern.col.numel(), dtype=F64, device=device)
    values[pattern.diagonal.reshape(-1)] = torch.arange(1.0, 9 * n + 1, dtype=F64, device=device)
    dense = _dense(pattern, values)
    blocks = torch.stack([dense[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n)])
    assert torch.equal(blocks.reshape(-1), torch.arange(1.0, 9 * n + 1, dtype=F64, device=device))
    assert float(dense.abs().sum()) == float(blocks.abs().sum())


def test_bad_input_names_the_problem(device):
    dof, p_kin, elements, n = _problem(device)
    index, hess = elements[0]
    pattern = assembly.block_pattern(assembly.block_keys(index, dof, n), n)
    values = torch.zeros(pattern.col.numel(), dtype=F64, device=device)
    rhs = torch.zeros(n, 3, dtype=F64, device=device)
    missing = torch.zeros(1, dtype=torch.int32, device=device)
    with pytest.raises(ValueError, match=r"hess \[N, 3k, 3k\]"):
        assembly.scatter_hessians(pattern, values, rhs, missing, index, hess[:, :6, :6], dof, p_kin)
    with pytest.raises(ValueError, match="float64"):
        assembly.scatter_hessians(pattern, values, rhs, missing, index, hess.float(), dof, p_kin)
    with pytest.raises(ValueError, match="rhs"):
        assembly.scatter_hessians(pattern, values, rhs[1:], missing, index, hess, dof, p_kin)
    with pytest.raises(ValueError, match="block keys"):
        assembly.block_pattern(torch.tensor([n * n], device=device), n)
