"""Taichi and Warp kernels, each behind a plain function on ``torch.Tensor``s.

Device choice lives in :mod:`kernels.backend`; NumPy/torch oracles of every kernel live in
:mod:`kernels.reference`. Nothing here initialises a backend at import.
"""

import os as _os

# Taichi prints a banner on import unless told not to; programs stay quiet unless they choose otherwise.
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
_os.environ.setdefault("TI_LOG_LEVEL", "warn")
