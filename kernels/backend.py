"""Device choice for Taichi and Warp, and zero-copy views between torch, Warp and Taichi.

One process runs its kernels on one device. Taichi holds a single architecture per process
(re-initialising it drops every compiled kernel and allocated field), so :func:`init` fixes the
device once: a second call with the same device is a no-op, one with another device raises.

Tensors are the currency between kernels and pipelines:

* Taichi kernels take ``torch.Tensor`` arguments directly through ``ti.types.ndarray()``; on the
  same device as the Taichi arch this is zero-copy (:func:`taichi_arg` checks that it will be).
* Warp kernels take ``wp.array`` views made by :func:`to_warp` (``wp.from_torch``, zero-copy), and
  :func:`to_torch` views a Warp array as a tensor. :func:`launch` launches a kernel on tensors directly, with a
  fraction of ``wp.launch``'s host work: for kernels launched many times a frame.
* :class:`CapturedCall` runs a function of tensors (torch operations and Warp launches) as one CUDA graph: for loops
  whose hundreds of small launches cost the host more time than the device.

On CUDA, Warp is set to launch on torch's current stream so that torch, Warp and Taichi work on a
tensor in program order without extra synchronisation.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import gc
import glob
import math
import os
import sys
import time

import torch

__all__ = [
    "CapturedCall",
    "DEVICES",
    "FRAMEWORKS",
    "PRECISIONS",
    "SMALL_GRID_BLOCK_DIM",
    "available_devices",
    "check_framework",
    "current_device",
    "default_device",
    "default_framework",
    "init",
    "launch",
    "one_torch_thread_on_cpu",
    "precision_dtype",
    "synchronize",
    "taichi_arg",
    "to_torch",
    "to_warp",
    "warp_launch",
    "torch_device",
    "load_warp_modules",
    "warp_arg",
    "warp_device",
]

DEVICES = ("cpu", "cuda")

FRAMEWORKS = ("taichi", "warp")
"""Kernel languages of the modules that keep a kernel in both (hash encoding, the renderer's per-round kernels)."""

PRECISIONS = {"auto": None, "float32": torch.float32, "float64": torch.float64}
"""Names of the precision settings that trade float64 for float32 in one part of a solver, and their dtypes;
``"auto"`` is resolved by :func:`precision_dtype`."""

SMALL_GRID_BLOCK_DIM = 64
"""CUDA threads a block for the Warp modules whose launches are a few thousand threads or fewer, each thread walking
a BVH or filling a float64 element matrix (the garment simulator's contact, candidate and element kernels, the
mesh queries): with Warp's default of 256 such a launch runs on a few of the GPU's streaming multiprocessors
(3.7k garment vertices: 15 blocks for an H200's 132) and waits on one thread's latency. 64 spreads it four times
wider and still lets a multiprocessor hold its full 2048 threads for large launches. A module takes it with
``wp.set_module_options({"block_dim": SMALL_GRID_BLOCK_DIM})``, which :func:`launch` and :func:`warp_launch` honour
(Warp's own launches use 256 unless told); CPU launches ignore it."""

_device: str | None = None


def available_devices() -> list[str]:
    """Devices this machine can run kernels on: ``["cpu"]`` plus ``"cuda"`` when torch sees a GPU."""
    return ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]


def default_device() -> str:
    """``"cuda"`` when present, else ``"cpu"``."""
    return available_devices()[-1]


def _check_device(device: str) -> str:
    if device not in DEVICES:
        raise ValueError(f"unknown device {device!r}; valid devices: {', '.join(DEVICES)}")
    if _device is not None and device != _device:
        raise RuntimeError(
            f"kernels are already initialised for {_device!r} in this process and cannot switch to "
            f"{device!r}; run a separate process with --device {device}"
        )
    if device not in available_devices():
        raise ValueError(
            f"device {device!r} is not available on this machine (available: {', '.join(available_devices())})"
        )
    return device


def default_framework(device: str | None = None) -> str:
    """The framework of a kernel kept in both languages, for ``device`` (default: the initialised one).

    Taichi on the CPU, where it runs a kernel on every core and Warp on one; Warp on CUDA, where a launch costs the
    host less. Its Python side checks a Taichi launch's argument types anew on each call, and the renderer's rounds
    are bound by the host (``docs/benchmarks.md``).
    """
    device = device or current_device() or default_device()
    return "warp" if device == "cuda" else "taichi"


def check_framework(framework: str | None) -> str:
    """``framework``, or :func:`default_framework` for ``None``; raises on an unknown one."""
    framework = framework or default_framework()
    if framework not in FRAMEWORKS:
        raise ValueError(f"unknown framework {framework!r}; valid: {', '.join(FRAMEWORKS)}")
    return framework


def precision_dtype(precision: str, device: torch.device | str) -> torch.dtype:
    """The dtype of a :data:`PRECISIONS` setting on ``device``: ``"auto"`` is float32 on CUDA, where single precision
    runs markedly faster, and float64 on the CPU, whose results then stay those of double precision."""
    dtype = PRECISIONS[precision]
    if dtype is None:
        dtype = torch.float32 if torch.device(device).type == "cuda" else torch.float64
    return dtype


def init(device: str | None = None) -> str:
    """Initialise Taichi and Warp for ``device`` once for the whole process.

    Args:
        device: ``"cpu"`` or ``"cuda"``; ``None`` picks :func:`default_device`, or keeps the device
            already chosen.

    Returns:
        The device in use.

    Raises:
        ValueError: the device is unknown or absent on this machine.
        RuntimeError: the process was already initialised for another device.
    """
    global _device
    if device is None:
        device = _device or default_device()
    _check_device(device)
    if _device is not None:
        return _device

    import taichi as ti
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    with _native_stderr_silenced(device == "cpu"):
        wp.init()
    ti.init(
        arch=ti.cuda if device == "cuda" else ti.cpu,
        default_fp=ti.f32,
        default_ip=ti.i32,
        offline_cache=True,
    )
    if device == "cuda":
        wp.set_stream(wp.stream_from_torch(torch.cuda.current_stream()), device="cuda:0")
    _device = device
    return device


@contextlib.contextmanager
def _native_stderr_silenced(silence: bool):
    """Discard what native code writes to the process's stderr while the block runs, when ``silence`` holds.

    Warp's library prints a warning straight to file descriptor 2 when it finds no CUDA driver; a CPU run asked for
    no GPU, so the warning only alarms. Python-level errors still raise as usual.
    """
    if not silence:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def current_device() -> str | None:
    """The device :func:`init` chose, or ``None`` before it ran."""
    return _device


def _require_init() -> str:
    if _device is None:
        raise RuntimeError("kernels.backend.init(device) must run before kernels are launched")
    return _device


def torch_device() -> torch.device:
    """The torch device matching the initialised backend."""
    return torch.device("cuda:0" if _require_init() == "cuda" else "cpu")


def warp_device() -> str:
    """The Warp device name matching the initialised backend (``"cpu"`` or ``"cuda:0"``)."""
    return "cuda:0" if _require_init() == "cuda" else "cpu"


def load_warp_modules(*modules) -> None:
    """Build (or load from Warp's kernel cache) the Warp kernels of these Python modules now, on the backend's
    device, rather than at their first launch: a solver whose kernels first launch mid-run (at the first contact,
    say) would otherwise stall there while an empty cache compiles them."""
    import warp as wp

    for module in modules:
        wp.load_module(module, device=warp_device())


def synchronize() -> None:
    """Wait for every kernel launched by torch, Warp and Taichi on the current device."""
    device = _require_init()
    if device == "cuda":
        import taichi as ti
        import warp as wp

        ti.sync()
        wp.synchronize_device("cuda:0")
        torch.cuda.synchronize()


def _check_on_device(tensor: torch.Tensor, what: str, strided: bool = False) -> None:
    if tensor.device.type != _require_init():
        expected = torch_device()
        raise ValueError(
            f"{what}: tensor is on {tensor.device}, kernels run on {expected}; move it with .to('{expected}')"
        )
    if not strided and not tensor.is_contiguous():
        raise ValueError(f"{what}: tensor is not contiguous; call .contiguous() first")


def to_warp(tensor: torch.Tensor, dtype=None, requires_grad: bool | None = None, strided: bool = False):
    """A zero-copy ``wp.array`` view of ``tensor``.

    Args:
        tensor: contiguous tensor on the backend's device.
        dtype: Warp dtype of the view, e.g. ``wp.vec3`` for a ``[N, 3]`` float32 tensor; ``None``
            keeps the scalar type.
        requires_grad: forwarded to ``wp.from_torch``.
        strided: accept any strides (a transposed view, say): the Warp array keeps the tensor's strides and its
            kernel indexes through them, so nothing is copied. For kernels written for such a layout only.
    """
    import warp as wp

    _check_on_device(tensor, "to_warp", strided)
    return wp.from_torch(tensor, dtype=dtype, requires_grad=requires_grad)


def warp_arg(tensor: torch.Tensor, dtype=None):
    """A zero-copy array descriptor of ``tensor`` to pass to ``wp.launch`` (checked as :func:`to_warp`).

    Cheaper to make than :func:`to_warp`'s ``wp.array`` (``wp.from_torch(..., return_ctype=True)``): for kernels
    launched many times a frame with fresh tensors, such as a renderer's rounds. It holds a reference to the
    tensor, so pass it straight to the launch.
    """
    import warp as wp

    _check_on_device(tensor, "warp_arg")
    return wp.from_torch(tensor, dtype=dtype, requires_grad=False, return_ctype=True)


class _Replay:
    """A launch of one kernel for one pattern of argument types, recorded once and replayed with fresh tensors.

    The array descriptors live in the recorded command's parameter block: a replay writes each tensor's address,
    shape and strides into its descriptor in place, so neither ``wp.array`` views nor Warp's argument packing run.
    """

    __slots__ = ("kernel", "command", "arrays", "dim")

    def __init__(self, kernel):
        self.kernel = kernel  # the concrete overload
        self.command = None  # the recorded wp.Launch
        self.arrays: list[tuple[int, object, int, int]] = []  # (argument, descriptor, element bytes, dtype dims)
        self.dim = 0

    def record(self, dim: int | tuple[int, ...], args: list, device: str) -> None:
        import warp as wp

        params = [
            warp_arg(a) if isinstance(a, torch.Tensor) else warp_arg(*a) if isinstance(a, tuple) else a for a in args
        ]
        block_dim = _block_dim(self.kernel, device)
        command = wp.launch(self.kernel, dim=dim, inputs=params, device=device, record_cmd=True, block_dim=block_dim)
        if not isinstance(command, wp.Launch):  # a launch Warp does not record (none, for zero threads)
            return
        for i, arg in enumerate(args):
            if isinstance(arg, (torch.Tensor, tuple)):
                tensor = arg if isinstance(arg, torch.Tensor) else arg[0]
                inner = len(getattr(arg[1], "_shape_", ())) if isinstance(arg, tuple) else 0
                descriptor = command.params[i + 1]  # what the launch reads
                descriptor._ref = descriptor._gradref = None  # the command outlives this call's tensors
                self.arrays.append((i, descriptor, tensor.element_size(), inner))
        self.command, self.dim = command, dim

    def replay(self, dim: int | tuple[int, ...], args: list) -> None:
        command, device_type = self.command, _require_init()
        for i, arg in enumerate(args):
            if type(arg) is float or type(arg) is int:
                command.params[i + 1].value = arg  # the ctypes scalar the kernel's argument type packed
            elif not isinstance(arg, (torch.Tensor, tuple)):
                command.set_param_at_index(i, arg)
        for i, descriptor, size, inner in self.arrays:
            arg = args[i]
            tensor = arg if isinstance(arg, torch.Tensor) else arg[0]
            if tensor.device.type != device_type or not tensor.is_contiguous():
                _check_on_device(tensor, "launch")  # raises
            shape = tensor.shape
            ndim = len(shape) - inner
            descriptor.data = tensor.data_ptr()
            if ndim == 0:  # the whole tensor is one element of the dtype, as wp.from_torch views it
                descriptor.shape[0], descriptor.strides[0] = 1, size
            else:
                strides = tensor.stride()
                for d in range(ndim):
                    descriptor.shape[d] = shape[d]
                    descriptor.strides[d] = strides[d] * size
        if dim != self.dim and _threads(dim) > 0:
            command.set_dim(dim)
            self.dim = dim


_REPLAYS: dict[tuple, _Replay] = {}


def _block_dim(kernel, device: str) -> int | None:
    """The block size of ``kernel``'s module (``wp.set_module_options({"block_dim": ...})``) for a CUDA launch, which
    Warp's launches do not read by themselves (they take 256 unless told); ``None`` on the CPU."""
    return kernel.module.options.get("block_dim") if device.startswith("cuda") else None


def warp_launch(kernel, dim: int | tuple[int, ...], **kwargs) -> None:
    """``wp.launch(kernel, dim, ...)`` (``inputs``, ``outputs``, ``device``) in blocks of the kernel module's own size
    (:data:`SMALL_GRID_BLOCK_DIM` where a module asks for it): for launches on ``wp.array`` arguments that
    :func:`launch` does not take."""
    import warp as wp

    device = str(kwargs.get("device") or warp_device())
    wp.launch(kernel, dim=dim, block_dim=_block_dim(kernel, device), **kwargs)


def launch(kernel, dim: int | tuple[int, ...], args: list) -> None:
    """Launch the Warp kernel ``kernel`` over ``dim`` threads (a count or a shape) on the backend's device, arguments
    in order.

    Each argument is a torch tensor (viewed as an array of its scalar type), a ``(tensor, warp_dtype)`` pair (viewed
    as an array of that dtype, e.g. ``(x, wp.vec3d)`` for a ``[N, 3]`` float64 tensor), or a scalar (a Python
    ``int`` or ``float``, or a Warp scalar such as ``wp.float64(0.5)``). Tensors go through :func:`to_warp`'s
    checks.

    ``wp.launch`` of a generic kernel (``Any``-typed arguments) infers the argument types and finds the overload at
    every launch, makes a ``wp.array`` view of each tensor and packs every argument, host time that exceeds the
    kernel itself for a few thousand elements. Here the first launch of each pattern of argument types is recorded
    (``wp.launch(..., record_cmd=True)``), and later ones write the tensors' addresses and shapes into the recorded
    descriptors and replay it (:class:`_Replay`), at about half the host time (``docs/benchmarks.md``,
    ``kernels.backend``).
    """
    device = warp_device()
    key = (kernel, device, *(_signature(a) for a in args))
    replay = _REPLAYS.get(key)
    if replay is None:
        concrete = kernel
        if kernel.is_generic:
            concrete = kernel.add_overload(kernel.infer_argument_types([_view(a) for a in args]))
        replay = _REPLAYS[key] = _Replay(concrete)
    if replay.command is None:
        replay.record(dim, args, device)
        if replay.command is None:
            return
    else:
        replay.replay(dim, args)
    if _threads(dim) > 0:
        replay.command.launch()


class CapturedCall:
    """A function of tensors, replayed on CUDA as one CUDA graph; on the CPU, simply called.

    ``fn`` takes no arguments: it reads its inputs from tensors whose storage stays put between calls (buffers the
    caller updates in place) and returns its outputs; it may write buffers too, but none that it reads (the first
    call runs it twice). It must not read the device from the host (no ``.item()``, ``.tolist()``, boolean-mask
    indexing or ``nonzero`` without a static size).

    On CUDA the first call runs ``fn`` once as it is (so that modules load and libraries make their handles and
    workspaces outside the capture), then captures it on a side stream, with Warp's launches sent to that stream,
    and replays the graph; every later call only replays it. A capture after :meth:`reset` skips that first run
    (unless the capture fails without it). The outputs are then the graph's own tensors: each
    call returns the same tensors, overwritten, so copy what must outlive the next call. :meth:`reset` drops the
    graph (for new input buffers, shapes or Python scalars, which the graph holds as they were at capture).
    ``capture=False`` makes every call a plain call (a caller whose inputs change shape from call to call).

    A replay costs the host about as much as one launch, where ``fn`` may make hundreds: a Newton iteration of the
    garment simulator makes about 270 torch operations and 30 Warp launches.
    """

    def __init__(self, fn, capture: bool = True):
        self.fn = fn
        self.capture = capture  # False: always a plain call (for callers whose inputs change shape)
        self.captures = 0  # how many times the graph was captured
        self.capture_seconds = 0.0  # host time those captures took
        self._graph = None
        self._outputs = None
        self._stream: torch.cuda.Stream | None = None

    def __call__(self):
        if not self.capture or _require_init() != "cuda":
            return self.fn()
        if self._graph is None:
            start = time.perf_counter()
            try:
                self._capture(warm_up=self._stream is None)
            except RuntimeError:  # something still loaded lazily, which a capture forbids: run it first, then again
                self._capture(warm_up=True)
            self.capture_seconds += time.perf_counter() - start
        self._graph.replay()
        return self._outputs

    def reset(self) -> None:
        """Forget the graph: the next call captures ``fn`` again."""
        self._graph = self._outputs = None

    def _capture(self, warm_up: bool) -> None:
        """Capture ``fn`` on this call's own side stream; ``warm_up`` runs it there once before (the first capture:
        modules, library handles and the stream's workspaces load outside the capture)."""
        import warp as wp

        device = warp_device()
        if self._stream is None:
            self._stream = torch.cuda.Stream()
        stream = self._stream
        stream.wait_stream(torch.cuda.current_stream())
        warp_stream = wp.get_stream(device)
        wp.set_stream(wp.stream_from_torch(stream), device=device)
        collecting = gc.isenabled()
        try:
            with torch.cuda.stream(stream):
                if warm_up:
                    self.fn()
                # No collection during the capture: a collected object that frees device memory or destroys a graph
                # (another solver's, say) would make an operation the capture forbids and void the graph. (Not
                # ``torch.cuda.graph``, which collects first, a full collection per capture: ``docs/benchmarks.md``.)
                # Thread-local mode: other threads' CUDA calls may go on.
                gc.disable()
                graph = torch.cuda.CUDAGraph()
                graph.capture_begin(capture_error_mode="thread_local")
                try:
                    outputs = self.fn()
                finally:
                    graph.capture_end()
        finally:
            if collecting:
                gc.enable()
            wp.set_stream(warp_stream, device=device)
        torch.cuda.current_stream().wait_stream(stream)
        self._graph, self._outputs = graph, outputs
        self.captures += 1


def _threads(dim: int | tuple[int, ...]) -> int:
    return math.prod(dim) if isinstance(dim, tuple) else dim


def _signature(arg) -> tuple | type:
    if isinstance(arg, torch.Tensor):
        return arg.dtype, arg.dim()
    if isinstance(arg, tuple):
        return arg[0].dtype, arg[0].dim(), arg[1]
    return type(arg)


def _view(arg):
    if isinstance(arg, torch.Tensor):
        return to_warp(arg)
    if isinstance(arg, tuple):
        return to_warp(arg[0], dtype=arg[1])
    return arg


def to_torch(array) -> torch.Tensor:
    """A zero-copy tensor view of a Warp array."""
    import warp as wp

    return wp.to_torch(array)


def taichi_arg(tensor: torch.Tensor) -> torch.Tensor:
    """Check that ``tensor`` can be passed to a ``ti.types.ndarray()`` argument without a copy.

    Taichi silently copies tensors that live on another device than its arch; this refuses them.
    """
    _check_on_device(tensor, "taichi_arg")
    return tensor


def nvidia_library_candidates(name: str, environment: str) -> list[str]:
    """Paths to try, in order, for the NVIDIA library ``lib{name}.so`` that :mod:`kernels.cudss` and
    :mod:`kernels.cusolver` bind with ``ctypes``: the path in ``$environment``, the ``nvidia`` wheels on ``sys.path``
    (``nvidia/cu13/lib``, ``nvidia/cu12/lib``, ``nvidia/{name}/lib``; torch's CUDA wheels bring them), the loader's
    search path."""
    found = []
    if os.environ.get(environment):
        found.append(os.environ[environment])
    for root in sys.path:
        for sub in ("nvidia/cu13/lib", "nvidia/cu12/lib", f"nvidia/{name}/lib"):
            found += sorted(glob.glob(os.path.join(root or ".", sub, f"lib{name}.so*")), reverse=True)
    library = ctypes.util.find_library(name)
    if library:
        found.append(library)
    return found


@contextlib.contextmanager
def one_torch_thread_on_cpu():
    """Limit torch to one intra-op thread while the kernels run on the CPU (a no-op on CUDA).

    Also a decorator. For loops of many small tensor operations (a cloth step's thousands of rows, a tracking
    iteration around the rasterizer): torch's intra-op threads cost more to wake than they save, and on shared cores
    they wait on each other (figures: ``docs/benchmarks.md``, ``kernels.backend``).
    """
    if torch_device().type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
