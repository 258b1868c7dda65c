"""Sparse symmetric positive definite solves on CUDA through NVIDIA cuDSS, bound with ``ctypes``.

cuDSS is optional: ``pip install nvidia-cudss-cu13`` (or ``-cu12``, matching torch's CUDA) makes
:func:`available` true. The library is found, in order, at the path in ``$CUDSS_LIBRARY``, in the
``nvidia`` wheels on ``sys.path``, or on the loader's search path. Versions 0.8 and later are supported
(0.8 gave the CSR constructor its offset type and the phases their present bit flags).

:class:`SparseSPDSolver` keeps one factorisation on the device. :meth:`~SparseSPDSolver.factor` runs cuDSS's
analysis (fill-reducing reordering on the host, symbolic factorisation) only when the sparsity pattern differs
from the last matrix's, then the numeric factorisation; :meth:`~SparseSPDSolver.solve` solves with it. Every
call runs on torch's current stream. :func:`blocks_to_csr` turns 3×3 COO blocks (duplicates summed) into the
scalar CSR arrays it takes; :func:`block_pattern_csr` gives the CSR structure of a block pattern, for callers
that assemble many matrices on one pattern.
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys

import torch

from kernels import backend

__all__ = ["CudssError", "SparseSPDSolver", "available", "block_pattern_csr", "blocks_to_csr", "version"]

# enumerators of cudss.h / library_types.h (stable from cuDSS 0.8 on)
_SUCCESS = 0
_STATUS = (
    "SUCCESS",
    "NOT_INITIALIZED",
    "ALLOC_FAILED",
    "INVALID_VALUE",
    "NOT_SUPPORTED",
    "EXECUTION_FAILED",
    "INTERNAL_ERROR",
    "IR_FAILED",
)
_PHASE_ANALYSIS = 0b11  # reordering | symbolic factorisation
_PHASE_FACTORIZATION = 1 << 2
_PHASE_SOLVE = 0b1111110000  # forward permutation … refinement
_CUDA_R_64F = 1
_CUDA_R_32I = 10
_MTYPE_SPD = 3
_MVIEW_FULL = 0
_BASE_ZERO = 0
_LAYOUT_COL_MAJOR = 0
_DATA_INFO = 0
_MINIMUM_VERSION = (0, 8)

_library: ctypes.CDLL | None = None
_load_error: str | None = None


class CudssError(RuntimeError):
    """A cuDSS call failed, or the library cannot be used."""


def _preload_dependencies(path: str) -> None:
    """Load the cuBLAS and NVRTC that ``path`` needs globally, from the ``nvidia`` wheels beside it or on
    ``sys.path`` (torch's own, when it was installed from wheels), so that the loader finds them.

    Loading a library twice is harmless: the loader keeps one copy per name."""
    lib = os.path.dirname(os.path.abspath(path))
    folders = [lib]
    for root in sys.path:
        folders += sorted(glob.glob(os.path.join(root or ".", "nvidia", "*", "lib")))
    for pattern in ("libcublasLt.so.*", "libcublas.so.*", "libnvrtc.so.*"):
        for folder in folders:
            for dependency in sorted(glob.glob(os.path.join(folder, pattern))):
                try:
                    ctypes.CDLL(dependency, mode=ctypes.RTLD_GLOBAL)
                except OSError:
                    pass


def _load() -> ctypes.CDLL:
    global _library, _load_error
    if _library is not None:
        return _library
    if _load_error is not None:
        raise CudssError(_load_error)
    errors = []
    for path in backend.nvidia_library_candidates("cudss", "CUDSS_LIBRARY"):
        try:
            library = ctypes.CDLL(path)
        except OSError:
            _preload_dependencies(path)
            try:
                library = ctypes.CDLL(path)
            except OSError as error:
                errors.append(f"{path}: {error}")
                continue
        _declare(library)
        found = _version_of(library)
        if found[:2] < _MINIMUM_VERSION:
            errors.append(f"{path}: version {'.'.join(map(str, found))} is older than 0.8")
            continue
        _library = library
        return library
    _load_error = (
        "cuDSS is not available ("
        + ("; ".join(errors) if errors else "no libcudss found")
        + "): pip install nvidia-cudss-cu13 (or nvidia-cudss-cu12 for a CUDA 12 torch), or set CUDSS_LIBRARY to "
        "the path of libcudss.so"
    )
    raise CudssError(_load_error)


def _declare(library: ctypes.CDLL) -> None:
    p, i64, c_int = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    signatures = {
        "cudssCreate": [ctypes.POINTER(p)],
        "cudssDestroy": [p],
        "cudssSetStream": [p, p],
        "cudssConfigCreate": [ctypes.POINTER(p)],
        "cudssConfigDestroy": [p],
        "cudssDataCreate": [p, ctypes.POINTER(p)],
        "cudssDataDestroy": [p, p],
        "cudssDataGet": [p, p, c_int, p, ctypes.c_size_t, ctypes.POINTER(ctypes.c_size_t)],
        "cudssMatrixCreateCsr": [ctypes.POINTER(p), i64, i64, i64, p, p, p, p, *[c_int] * 6],
        "cudssMatrixCreateDn": [ctypes.POINTER(p), i64, i64, i64, p, c_int, c_int],
        "cudssMatrixSetValues": [p, p],
        "cudssMatrixDestroy": [p],
        "cudssExecute": [p, c_int, p, p, p, p, p],
        "cudssGetProperty": [c_int, ctypes.POINTER(c_int)],
    }
    for name, argtypes in signatures.items():
        function = getattr(library, name)
        function.argtypes = argtypes
        function.restype = c_int


def _version_of(library: ctypes.CDLL) -> tuple[int, int, int]:
    parts = []
    for prop in range(3):  # MAJOR_VERSION, MINOR_VERSION, PATCH_LEVEL
        value = ctypes.c_int()
        library.cudssGetProperty(prop, ctypes.byref(value))
        parts.append(value.value)
    return tuple(parts)


def available() -> bool:
    """Whether cuDSS (0.8 or later) loads and torch sees a CUDA device."""
    if not torch.cuda.is_available():
        return False
    try:
        _load()
    except CudssError:
        return False
    return True


def version() -> tuple[int, int, int]:
    """cuDSS's ``(major, minor, patch)``; raises :class:`CudssError` when it cannot be loaded."""
    return _version_of(_load())


def _check(status: int, call: str) -> None:
    if status != _SUCCESS:
        name = _STATUS[status] if 0 <= status < len(_STATUS) else str(status)
        raise CudssError(f"{call} failed with CUDSS_STATUS_{name}")


class SparseSPDSolver:
    """Cholesky factorisation of a sparse SPD matrix on a CUDA device, reused across right-hand sides.

    Args:
        device: the CUDA device the matrices and right-hand sides live on.

    Attributes:
        analyses: how many times the pattern was analysed (reordered and factored symbolically).
        factorizations: how many numeric factorisations ran.
    """

    def __init__(self, device: torch.device | str = "cuda"):
        self.device = torch.device(device)
        if self.device.type != "cuda":
            raise ValueError(f"cuDSS solves on a CUDA device, got {self.device}")
        self._lib = _load()
        self._handle, self._config, self._data = ctypes.c_void_p(), ctypes.c_void_p(), ctypes.c_void_p()
        with torch.cuda.device(self.device):
            _check(self._lib.cudssCreate(ctypes.byref(self._handle)), "cudssCreate")
            _check(self._lib.cudssConfigCreate(ctypes.byref(self._config)), "cudssConfigCreate")
            _check(self._lib.cudssDataCreate(self._handle, ctypes.byref(self._data)), "cudssDataCreate")
        self._matrix = ctypes.c_void_p()
        self._pattern: tuple[torch.Tensor, torch.Tensor] | None = None
        self._values: torch.Tensor | None = None
        self._size = 0
        self.analyses = 0
        self.factorizations = 0

    def factor(self, crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor) -> bool:
        """Factor the matrix given as CSR arrays (every stored entry of both triangles, float64).

        The analysis is kept while the pattern stays the same. Passing the very ``crow`` and ``col`` tensors (int32,
        on the device) of the last call says so without comparing them, which saves two reads from the device.

        Returns whether it is positive definite (a ``False`` leaves no usable factor).
        """
        self.queue_factor(crow, col, values)
        return self.positive_definite()

    def queue_factor(self, crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor) -> None:
        """:meth:`factor` without waiting for the factorisation to finish: a :meth:`solve` may be queued behind it,
        and :meth:`positive_definite` says later whether both are valid (the status is a read from the device)."""
        crow = crow.to(self.device, torch.int32).contiguous()
        col = col.to(self.device, torch.int32).contiguous()
        values = values.to(self.device, torch.float64).contiguous()
        last = self._pattern
        same = last is not None and last[0] is crow and last[1] is col
        if not same:
            if col.numel() != values.numel() or col.numel() != int(crow[-1]):
                raise ValueError(
                    f"CSR arrays disagree: {col.numel()} column indices, {values.numel()} values, last offset "
                    f"{int(crow[-1])}"
                )
            same = (
                last is not None
                and (last[0].numel(), last[1].numel()) == (crow.numel(), col.numel())
                and bool(torch.equal(last[0], crow) and torch.equal(last[1], col))
            )
        elif values.numel() != col.numel():
            raise ValueError(f"{values.numel()} values for a pattern of {col.numel()} entries")
        lib = self._lib
        with torch.cuda.device(self.device):
            self._set_stream()
            if same:
                _check(lib.cudssMatrixSetValues(self._matrix, values.data_ptr()), "cudssMatrixSetValues")
            else:
                self._destroy_matrix()
                size = crow.numel() - 1
                _check(
                    lib.cudssMatrixCreateCsr(
                        ctypes.byref(self._matrix), size, size, col.numel(), crow.data_ptr(), None, col.data_ptr(),
                        values.data_ptr(), _CUDA_R_32I, _CUDA_R_32I, _CUDA_R_64F, _MTYPE_SPD, _MVIEW_FULL,
                        _BASE_ZERO,
                    ),
                    "cudssMatrixCreateCsr",
                )
                self._pattern, self._size = (crow, col), size
                self._execute(_PHASE_ANALYSIS, None, None, "analysis")
                self.analyses += 1
            self._values = values  # cuDSS reads the values through this pointer
            self._execute(_PHASE_FACTORIZATION, None, None, "factorization")
            self.factorizations += 1

    def positive_definite(self) -> bool:
        """Whether the last factorisation met only positive pivots (it waits for that factorisation)."""
        if self._pattern is None:
            raise CudssError("positive_definite before factor: factor a matrix first")
        info = ctypes.c_int()
        written = ctypes.c_size_t()
        with torch.cuda.device(self.device):
            _check(
                self._lib.cudssDataGet(
                    self._handle, self._data, _DATA_INFO, ctypes.byref(info), 4, ctypes.byref(written)
                ),
                "cudssDataGet(INFO)",
            )
        return info.value == 0

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """Solve with the last factor: ``rhs`` is ``[n]`` or ``[n, k]`` float64 on the device."""
        if self._pattern is None:
            raise CudssError("solve before factor: factor a matrix first")
        if rhs.shape[0] != self._size:
            raise ValueError(f"right-hand side has {rhs.shape[0]} rows, the factored matrix {self._size}")
        columns = 1 if rhs.dim() == 1 else rhs.shape[1]
        b = rhs.to(self.device, torch.float64).reshape(self._size, columns).t().contiguous()  # column-major
        x = torch.empty_like(b)
        lib = self._lib
        mb, mx = ctypes.c_void_p(), ctypes.c_void_p()
        with torch.cuda.device(self.device):
            self._set_stream()
            for matrix, array in ((mb, b), (mx, x)):
                _check(
                    lib.cudssMatrixCreateDn(
                        ctypes.byref(matrix), self._size, columns, self._size, array.data_ptr(), _CUDA_R_64F,
                        _LAYOUT_COL_MAJOR,
                    ),
                    "cudssMatrixCreateDn",
                )
            try:
                self._execute(_PHASE_SOLVE, mx, mb, "solve")
            finally:
                lib.cudssMatrixDestroy(mb)
                lib.cudssMatrixDestroy(mx)
        x = x.t()
        return x[:, 0] if rhs.dim() == 1 else x

    def _set_stream(self) -> None:
        stream = torch.cuda.current_stream(self.device).cuda_stream
        _check(self._lib.cudssSetStream(self._handle, ctypes.c_void_p(stream)), "cudssSetStream")

    def _execute(self, phase: int, solution, rhs, name: str) -> None:
        _check(
            self._lib.cudssExecute(self._handle, phase, self._config, self._data, self._matrix, solution, rhs),
            f"cudssExecute({name})",
        )

    def _destroy_matrix(self) -> None:
        if self._matrix.value:
            self._lib.cudssMatrixDestroy(self._matrix)
            self._matrix = ctypes.c_void_p()

    def close(self) -> None:
        """Free the factor and the library handle (also done when the solver is collected)."""
        if getattr(self, "_handle", None) is None or not self._handle.value:
            return
        self._destroy_matrix()
        self._lib.cudssDataDestroy(self._handle, self._data)
        self._lib.cudssConfigDestroy(self._config)
        self._lib.cudssDestroy(self._handle)
        self._handle = ctypes.c_void_p()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may be gone already
            pass


def block_pattern_csr(
    block_rows: torch.Tensor, block_cols: torch.Tensor, n: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scalar CSR structure of a ``3n × 3n`` matrix made of 3×3 blocks at distinct ``(block_rows, block_cols)``,
    sorted by row, then column.

    Returns ``(crow [3n + 1], col [9K], position [K, 3, 3])``: the values array of block ``k``'s entry ``(a, b)``
    is at ``position[k, a, b]`` (``values[position] = blocks``).
    """
    device = block_rows.device
    block_rows, block_cols = block_rows.to(torch.int64), block_cols.to(torch.int64)
    count = torch.bincount(block_rows, minlength=n)
    start = torch.zeros(n + 1, dtype=torch.int64, device=device)
    start[1:] = torch.cumsum(count, 0)
    # scalar row 3i + a holds, for each block k of block row i in order, the columns 3 col_k + b (b = 0, 1, 2)
    a = torch.arange(3, device=device)
    crow = torch.empty(3 * n + 1, dtype=torch.int64, device=device)
    crow[:-1] = (9 * start[:-1, None] + 3 * a[None, :] * count[:, None]).reshape(-1)
    crow[-1:] = 9 * start[-1:]
    within = torch.arange(block_rows.numel(), device=device) - start[block_rows]
    position = (
        9 * start[block_rows][:, None, None]
        + 3 * a[None, :, None] * count[block_rows][:, None, None]
        + 3 * within[:, None, None]
        + a[None, None, :]
    )
    col = torch.empty(9 * block_rows.numel(), dtype=torch.int64, device=device)
    col[position.reshape(-1)] = (3 * block_cols[:, None, None] + a[None, None, :]).expand(-1, 3, 3).reshape(-1)
    return crow, col, position


def blocks_to_csr(
    rows: torch.Tensor, cols: torch.Tensor, blocks: torch.Tensor, n: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scalar CSR arrays ``(crow [3n + 1], col, values)`` of the ``3n × 3n`` matrix given as 3×3 COO blocks.

    Blocks at the same ``(row, col)`` are summed; columns are sorted within each row. Pure torch, on the blocks'
    device (one host read: the number of distinct blocks).
    """
    key = rows.to(torch.int64) * n + cols.to(torch.int64)
    unique, inverse = torch.unique(key, sorted=True, return_inverse=True)
    summed = blocks.new_zeros(unique.numel(), 3, 3).index_add_(0, inverse, blocks)
    crow, col, position = block_pattern_csr(unique // n, unique % n, n)
    values = torch.empty(col.numel(), dtype=blocks.dtype, device=blocks.device)
    values[position.reshape(-1)] = summed.reshape(-1)
    return crow, col, values
