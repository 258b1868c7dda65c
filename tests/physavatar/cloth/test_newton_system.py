"""Newton matrices of the garment simulator: a block pattern that grows once per new pair and outlives the step."""

import torch

from kernels import backend, cudss, element_terms
from kernels.reference.assembly import newton_matrix
from physavatar.cloth.newton_system import NewtonElement, NewtonMatrices, filtered_elements
from physavatar.shapes import grid_sheet

F64 = torch.float64


def test_newton_pattern_grows_once_per_new_pair_and_outlives_the_step(device):
    """The Newton matrices keep the garment's pattern; a self-contact joining two vertices for the first time grows it
    once, and it stays for the next step (cuDSS analyses it once). New free vertices restart it. Every matrix is the
    dense sum of its blocks, with the kinematic vertices' blocks on the right-hand side."""
    _, faces = grid_sheet(3, 3, 0.1)  # 9 vertices
    torch_device = backend.torch_device()
    faces = faces.to(torch_device, torch.int32)
    g = torch.Generator().manual_seed(3)

    def spd(count: int, size: int) -> torch.Tensor:
        a = torch.randn(count, size, size, generator=g, dtype=F64)
        return (a @ a.transpose(1, 2) + size * torch.eye(size, dtype=F64)).to(torch_device)

    def dofs(kinematic: list[int]) -> torch.Tensor:
        dof = torch.full((9,), -1, dtype=torch.int32)
        free = [i for i in range(9) if i not in kinematic]
        dof[free] = torch.arange(len(free), dtype=torch.int32)
        return dof.to(torch_device)

    membrane = NewtonElement(faces, spd(faces.shape[0], 9), 0.5, "abs", None)
    far = torch.tensor([[0, 8, 2, 6]], dtype=torch.int32, device=torch_device)  # corners no triangle joins
    contact = NewtonElement(far, spd(1, 12), 0.5, "clamp", far)
    matrices = NewtonMatrices([faces])
    p_kin = torch.randn(9, 3, generator=g, dtype=F64).to(torch_device)
    solver = cudss.SparseSPDSolver(torch_device) if device == "cuda" and cudss.available() else None
    patterns = []
    for elements, kinematic in (
        ([membrane], [4]),
        ([membrane, contact], [4]),  # grows
        ([membrane, contact], [4]),  # a new step, the same free vertices: kept
        ([membrane], [4]),
        ([membrane, contact], [4, 5]),  # new free vertices: restarts from the garment, then grows
    ):
        dof = dofs(kinematic)
        n = int((dof >= 0).sum())
        rhs = torch.randn(n, 3, generator=g, dtype=F64).to(torch_device)
        push = p_kin * (dof < 0)[:, None]
        matrix, out = matrices.assemble(elements, rhs, dof, push, None)
        expected, pushed = newton_matrix(n, [(e.index, e.hess, e.scale) for e in elements], dof, push)
        torch.testing.assert_close(matrix.to_dense(), expected, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out, rhs + pushed, rtol=1e-12, atol=1e-12)
        patterns.append(matrix.pattern)
        if solver is not None:
            assert solver.factor(matrix.pattern.crow, matrix.pattern.col, matrix.values)
            x = solver.solve(out.reshape(-1))
            torch.testing.assert_close(expected @ x, out.reshape(-1), rtol=1e-10, atol=1e-10)
    assert patterns[0] is not patterns[1] and patterns[1] is patterns[2] is patterns[3]
    assert patterns[4] is not patterns[3] and patterns[4].n == 7
    if solver is not None:
        assert solver.analyses == 3

    # the Newton loop scatters without reading: the blocks outside the pattern are counted on the device and bounded
    # on the diagonal (the matrix exceeds the exact one by a PSD term), and the pattern grows at the next step
    fresh, dof, elements = NewtonMatrices([faces]), dofs([4]), [membrane, contact]
    rhs = torch.randn(8, 3, generator=g, dtype=F64).to(torch_device)
    push = p_kin * (dof < 0)[:, None]
    active = fresh.prepare(elements, dof, 8)
    matrix, out, missing = fresh.scatter(active, rhs, dof, push, None)
    expected, pushed = newton_matrix(8, [(e.index, e.hess, e.scale) for e in elements], dof, push)
    assert int(missing) > 0
    assert float(torch.linalg.eigvalsh(matrix.to_dense() - expected).min()) > -1e-9
    torch.testing.assert_close(out, rhs + pushed, rtol=1e-12, atol=1e-12)
    before = fresh.pattern
    fresh.defer(elements, dof, 8)
    assert fresh.pattern is before
    dof = dofs([4])  # the next step, with the same free vertices
    matrix, out, missing = fresh.scatter(fresh.prepare(elements, dof, 8), rhs, dof, push, None)
    assert fresh.pattern is not before and int(missing) == 0
    torch.testing.assert_close(matrix.to_dense(), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out, rhs + pushed, rtol=1e-12, atol=1e-12)


def test_barrier_hessians_are_filtered_in_float64_whatever_the_elastic_precision(device):
    """A barrier Hessian near contact: a stiffness of 10¹² along the pair's normal over ones of order 1 across it. With
    float32 decompositions for the elastic elements, the barrier's are still decomposed in float64, so the small
    eigenvalues (the directions the garment slides in) keep their values; an element not so marked gets float32's."""
    torch_device = backend.torch_device()
    g = torch.Generator().manual_seed(5)
    basis, _ = torch.linalg.qr(torch.randn(4, 12, 12, generator=g, dtype=F64))
    values = torch.linspace(-1.0, 2.0, 12, dtype=F64).repeat(4, 1)
    values[:, -1] = 1e12
    hess = ((basis * values[:, None, :]) @ basis.transpose(1, 2)).to(torch_device)
    index = torch.arange(16, dtype=torch.int32, device=torch_device).view(4, 4)
    barrier = NewtonElement(index, hess, 1.0, "clamp", index, exact_psd=True)
    elastic = NewtonElement(index, hess, 1.0, "clamp", None)
    exact = element_terms.project_psd(hess)
    filtered_barrier, filtered_elastic = filtered_elements([barrier, elastic], torch.float32)
    assert torch.equal(filtered_barrier.hess, exact) and filtered_barrier.projection == "none"
    kept = torch.linalg.eigvalsh(filtered_barrier.hess.cpu())[:, :-1]  # all but the normal's
    torch.testing.assert_close(kept, values[:, :-1].clamp_min(0.0), rtol=0.0, atol=1e-2)  # 10¹² · float64 ε
    # float32's rounding, relative to 10¹², swamps the sliding directions' stiffness
    rounded = torch.linalg.eigvalsh(filtered_elastic.hess.cpu())[:, :-1]
    assert float((rounded - values[:, :-1].clamp_min(0.0)).abs().max()) > 10.0
