"""Batched eigen-decompositions of small symmetric matrices on CUDA: cuSOLVER's ``syevjBatched``, bound with ``ctypes``.

The garment simulator filters every element Hessian (9×9 membrane, 12×12 bending and contact) through its
eigen-decomposition, once per Newton iteration. ``torch.linalg.eigh`` on a CUDA batch runs cuSOLVER's
divide-and-conquer batched solver and then reads its error codes back, so every call waits for the device. The
Jacobi solver ``syevjBatched`` is built for batches of matrices up to 32×32 (one matrix per thread block, in
shared memory) and leaves its status on the device; over the garment's batches it is the faster of the two on
CUDA, with reconstructions ``Q Λ Qᵀ`` within 3e-14 of the input (``docs/benchmarks.md``, ``kernels.cusolver``).

The library comes with torch's CUDA wheels (``nvidia/cu13/lib`` or ``nvidia/cusolver/lib`` on ``sys.path``); the
path in ``$CUSOLVER_LIBRARY`` goes first, the loader's search path last. :func:`available` says whether it loads.
"""

from __future__ import annotations

import ctypes

import torch

from kernels import backend

__all__ = ["CusolverError", "MAX_SIZE", "available", "eigh"]

MAX_SIZE = 32
"""Largest matrix side ``syevjBatched`` takes."""

_SUCCESS = 0
_EIG_MODE_VECTOR = 1
_FILL_MODE_LOWER = 0
_STATUS = {
    1: "NOT_INITIALIZED",
    2: "ALLOC_FAILED",
    3: "INVALID_VALUE",
    4: "ARCH_MISMATCH",
    5: "MAPPING_ERROR",
    6: "EXECUTION_FAILED",
    7: "INTERNAL_ERROR",
    8: "MATRIX_TYPE_NOT_SUPPORTED",
    9: "NOT_SUPPORTED",
}

_library: ctypes.CDLL | None = None
_load_error: str | None = None
_handles: dict[int, tuple[ctypes.c_void_p, ctypes.c_void_p]] = {}  # device index → (handle, syevj parameters)


class CusolverError(RuntimeError):
    """A cuSOLVER call failed, or the library cannot be used."""


def _load() -> ctypes.CDLL:
    global _library, _load_error
    if _library is not None:
        return _library
    if _load_error is not None:
        raise CusolverError(_load_error)
    errors = []
    for path in backend.nvidia_library_candidates("cusolver", "CUSOLVER_LIBRARY"):
        try:
            library = ctypes.CDLL(path)
        except OSError as error:
            errors.append(f"{path}: {error}")
            continue
        _declare(library)
        _library = library
        return library
    _load_error = (
        "cuSOLVER is not available ("
        + ("; ".join(errors) if errors else "no libcusolver found")
        + "): it comes with torch's CUDA wheels (nvidia-cusolver); or set CUSOLVER_LIBRARY to the path of "
        "libcusolver.so"
    )
    raise CusolverError(_load_error)


def _declare(library: ctypes.CDLL) -> None:
    p, c_int = ctypes.c_void_p, ctypes.c_int
    buffer_size = [p, c_int, c_int, c_int, p, c_int, p, ctypes.POINTER(c_int), p, c_int]
    solve = [p, c_int, c_int, c_int, p, c_int, p, p, c_int, p, p, c_int]
    signatures = {
        "cusolverDnCreate": [ctypes.POINTER(p)],
        "cusolverDnSetStream": [p, p],
        "cusolverDnCreateSyevjInfo": [ctypes.POINTER(p)],
        "cusolverDnSsyevjBatched_bufferSize": buffer_size,
        "cusolverDnDsyevjBatched_bufferSize": buffer_size,
        "cusolverDnSsyevjBatched": solve,
        "cusolverDnDsyevjBatched": solve,
    }
    for name, argtypes in signatures.items():
        function = getattr(library, name)
        function.argtypes = argtypes
        function.restype = c_int


def _check(status: int, call: str) -> None:
    if status != _SUCCESS:
        raise CusolverError(f"{call} failed with CUSOLVER_STATUS_{_STATUS.get(status, status)}")


def available() -> bool:
    """Whether torch sees a CUDA device and cuSOLVER loads."""
    if not torch.cuda.is_available():
        return False
    try:
        _load()
    except CusolverError:
        return False
    return True


def _handle(device: torch.device) -> tuple[ctypes.c_void_p, ctypes.c_void_p]:
    index = device.index if device.index is not None else torch.cuda.current_device()
    if index not in _handles:
        lib = _load()
        handle, params = ctypes.c_void_p(), ctypes.c_void_p()
        with torch.cuda.device(index):
            _check(lib.cusolverDnCreate(ctypes.byref(handle)), "cusolverDnCreate")
        # default parameters: tolerance of the working precision, at most 100 sweeps, eigenvalues sorted
        _check(lib.cusolverDnCreateSyevjInfo(ctypes.byref(params)), "cusolverDnCreateSyevjInfo")
        _handles[index] = (handle, params)
    return _handles[index]


def eigh(hess: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eigen-decompositions ``Q Λ Qᵀ`` of a batch of symmetric matrices on a CUDA device, without waiting for them.

    Args:
        hess: ``[N, n, n]`` float32 or float64 symmetric matrices on a CUDA device, ``n ≤`` :data:`MAX_SIZE` (only
            the lower triangles are read).

    Returns:
        ``(eigenvalues [N, n] ascending, eigenvectors [N, n, n] as columns, info [N] int32)``, all on the device.
        ``info`` is nonzero where Jacobi's 100 sweeps ended before the working precision's tolerance was met (the
        eigenpairs are then those of the last sweep); it is not read here, so nothing waits for the device.

    Raises:
        ValueError: not a batch of square float matrices on CUDA, or larger than :data:`MAX_SIZE`.
        CusolverError: the library cannot be loaded or a call fails.
    """
    if hess.dim() != 3 or hess.shape[1] != hess.shape[2]:
        raise ValueError(f"hess must be [N, n, n], got {list(hess.shape)}")
    if hess.device.type != "cuda" or hess.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"hess must be float32 or float64 on a CUDA device, got {hess.dtype} on {hess.device}")
    count, n = hess.shape[0], hess.shape[1]
    if n > MAX_SIZE:
        raise ValueError(f"syevjBatched takes matrices up to {MAX_SIZE}×{MAX_SIZE}, got {n}×{n}; use torch.linalg.eigh")
    # column-major storage of a symmetric matrix is its row-major storage; the solver overwrites it with Qᵀ's
    vectors = hess.contiguous().clone()
    values = hess.new_empty(count, n)
    info = torch.zeros(count, dtype=torch.int32, device=hess.device)
    if count == 0:
        return values, vectors, info
    lib = _load()
    handle, params = _handle(hess.device)
    prefix = "cusolverDnD" if hess.dtype == torch.float64 else "cusolverDnS"
    size, solve = getattr(lib, prefix + "syevjBatched_bufferSize"), getattr(lib, prefix + "syevjBatched")
    a, w = ctypes.c_void_p(vectors.data_ptr()), ctypes.c_void_p(values.data_ptr())
    lwork = ctypes.c_int()
    with torch.cuda.device(hess.device):
        stream = torch.cuda.current_stream(hess.device).cuda_stream
        _check(lib.cusolverDnSetStream(handle, ctypes.c_void_p(stream)), "cusolverDnSetStream")
        _check(
            size(handle, _EIG_MODE_VECTOR, _FILL_MODE_LOWER, n, a, n, w, ctypes.byref(lwork), params, count),
            prefix + "syevjBatched_bufferSize",
        )
        work = hess.new_empty(max(lwork.value, 1))
        _check(
            solve(
                handle, _EIG_MODE_VECTOR, _FILL_MODE_LOWER, n, a, n, w, ctypes.c_void_p(work.data_ptr()),
                lwork.value, ctypes.c_void_p(info.data_ptr()), params, count,
            ),
            prefix + "syevjBatched",
        )  # fmt: skip
    return values, vectors.transpose(1, 2), info
