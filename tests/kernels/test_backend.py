import gc
import weakref
from typing import Any

import pytest
import taichi as ti
import torch
import warp as wp

from kernels import backend
from kernels.copy import copy_taichi, copy_warp


@ti.kernel
def _add_one(x: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in x:
        x[i] += 1.0


@wp.kernel
def _double(x: wp.array(dtype=wp.float32)):
    i = wp.tid()
    x[i] = 2.0 * x[i]


@wp.kernel
def _axpy(a: Any, x: wp.array(dtype=Any), y: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    i = wp.tid()
    out[i] = a * x[i] + y[i]


@wp.kernel
def _scaled_rows(
    index: wp.array2d(dtype=wp.int32), x: wp.array(dtype=wp.vec3d), a: wp.float64, out: wp.array2d(dtype=wp.vec3d)
):
    i, j = wp.tid()
    out[i, j] = a * x[index[i, j]]


def test_taichi_and_warp_share_one_tensor(device):
    x = torch.arange(1000, dtype=torch.float32, device=backend.torch_device())
    pointer = x.data_ptr()
    _add_one(backend.taichi_arg(x))
    view = backend.to_warp(x)
    assert view.ptr == pointer, "Warp view must alias the tensor's memory"
    wp.launch(_double, dim=x.numel(), inputs=[view], device=backend.warp_device())
    _add_one(backend.taichi_arg(x))
    backend.synchronize()
    expected = 2.0 * (torch.arange(1000, dtype=torch.float32) + 1.0) + 1.0
    assert x.data_ptr() == pointer
    torch.testing.assert_close(x.cpu(), expected)
    assert backend.to_torch(view).data_ptr() == pointer


@pytest.mark.parametrize("copy", [copy_taichi, copy_warp])
@pytest.mark.parametrize("length", [12345, 4096])  # scalar and 4-vector paths
def test_copy_kernels_match_reference(device, copy, length):
    src = torch.randn(length, device=backend.torch_device())
    dst = torch.zeros_like(src)
    copy(src, dst)
    backend.synchronize()
    torch.testing.assert_close(dst, src, rtol=0, atol=0)


def test_copy_rejects_mismatched_shapes(device):
    src = torch.zeros(4, device=backend.torch_device())
    with pytest.raises(ValueError, match="one shape"):
        copy_warp(src, torch.zeros(5, device=backend.torch_device()))


def test_init_is_idempotent_and_refuses_a_switch(device):
    assert backend.init(device) == device
    assert backend.init() == device
    other = "cuda" if device == "cpu" else "cpu"
    with pytest.raises(RuntimeError, match="cannot switch"):
        backend.init(other)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_launch_takes_tensors_vector_views_and_scalars(device, dtype):
    """One generic kernel launched on scalar arrays and on 3-vector views, in both precisions: each pattern of
    argument types gets its own overload, which later launches reuse."""
    g = torch.Generator().manual_seed(0)
    x, y = (torch.randn(7, 3, generator=g, dtype=dtype).to(backend.torch_device()) for _ in range(2))
    scalar, vec3 = (wp.float64, wp.vec3d) if dtype == torch.float64 else (wp.float32, wp.vec3f)
    out = torch.empty_like(x)
    for _ in range(2):
        backend.launch(_axpy, 7, [scalar(2.0), (x, vec3), (y, vec3), (out, vec3)])
        torch.testing.assert_close(out, 2.0 * x + y, rtol=0, atol=0)
    flat = torch.empty(21, dtype=dtype, device=x.device)
    backend.launch(_axpy, 21, [scalar(-1.0), x.view(-1), y.view(-1), flat])
    torch.testing.assert_close(flat, y.view(-1) - x.view(-1), rtol=0, atol=0)
    with pytest.raises(ValueError, match="contiguous"):
        backend.launch(_axpy, 7, [scalar(2.0), (x.t(), vec3), (y, vec3), (out, vec3)])


def test_replayed_launches_read_each_calls_tensors_shapes_and_scalars(device):
    """Later launches of one pattern of argument types replay the first one's recorded command: each must see its
    own tensors (addresses, shapes, 2-d strides), scalars and thread count, and zero threads must run nothing."""
    g = torch.Generator().manual_seed(1)
    cases = [(5, 4, 2, 0.5), (0, 3, 1, 9.0), (9, 6, 3, -2.0), (9, 6, 3, 3.0), (2, 11, 5, 1.25)]
    for rows, points, width, a in cases:
        x = torch.randn(points, 3, generator=g, dtype=torch.float64).to(backend.torch_device())
        index = torch.randint(0, points, (rows, width), generator=g, dtype=torch.int32).to(x.device)
        out = torch.full((rows, width, 3), 7.0, dtype=torch.float64, device=x.device)
        backend.launch(_scaled_rows, (rows, width), [index, (x, wp.vec3d), a, (out, wp.vec3d)])
        torch.testing.assert_close(out, a * x[index.long()], rtol=0, atol=0)
    if device == "cuda":
        with pytest.raises(ValueError, match="move it"):
            backend.launch(_scaled_rows, (rows, width), [index.cpu(), (x, wp.vec3d), a, (out, wp.vec3d)])


def test_recorded_and_replayed_launches_keep_no_tensor_alive(device):
    for _ in range(2):  # recorded, then replayed
        x = torch.ones(5, dtype=torch.float32, device=backend.torch_device())
        alive = weakref.ref(x)
        backend.launch(_double, 5, [x])
        backend.synchronize()
        assert x.tolist() == [2.0] * 5
        del x
        gc.collect()
        assert alive() is None


def test_unknown_device_names_the_valid_ones():
    with pytest.raises(ValueError, match="valid devices: cpu, cuda"):
        backend.init("tpu")


def test_tensor_on_wrong_device_is_refused(device):
    if device == "cpu":
        pytest.skip("needs a second device to put the tensor on")
    with pytest.raises(ValueError, match="move it"):
        backend.taichi_arg(torch.zeros(3))


def test_one_torch_thread_on_cpu_limits_and_restores_the_thread_count(device):
    before = torch.get_num_threads()

    @backend.one_torch_thread_on_cpu()
    def inside():
        return torch.get_num_threads()

    assert inside() == (1 if device == "cpu" else before)
    with pytest.raises(RuntimeError):
        with backend.one_torch_thread_on_cpu():
            raise RuntimeError("the count is restored on errors too")
    assert torch.get_num_threads() == before


def test_nvidia_libraries_are_looked_for_at_the_environments_path_first(monkeypatch, tmp_path):
    monkeypatch.setenv("EXAMPLE_LIBRARY", "/opt/example/libexample.so")
    wheel = tmp_path / "nvidia" / "example" / "lib"
    wheel.mkdir(parents=True)
    (wheel / "libexample.so.2").touch()
    monkeypatch.syspath_prepend(str(tmp_path))
    found = backend.nvidia_library_candidates("example", "EXAMPLE_LIBRARY")
    assert found[:2] == ["/opt/example/libexample.so", str(wheel / "libexample.so.2")]


def test_captured_call_follows_its_buffers(device):
    """A function of torch operations and Warp launches, called through CapturedCall: each call gives what a plain
    call would, from the values its input buffers hold then (on CUDA one CUDA graph, captured once)."""
    torch_device = backend.torch_device()
    x = torch.arange(6, dtype=torch.float64, device=torch_device)
    y = torch.ones(6, dtype=torch.float64, device=torch_device)

    def fn():
        out = torch.empty_like(x)
        backend.launch(_axpy, x.numel(), [wp.float64(3.0), x, y, out])
        return out, (out * out).sum(), torch.nonzero_static(out > 10.0, size=4, fill_value=-1).squeeze(1)

    call = backend.CapturedCall(fn)
    for step in range(3):
        x.mul_(2.0).add_(step)  # in place: the buffer the graph reads
        y.fill_(float(step))
        out, total, rows = call()
        want = 3.0 * x + y
        torch.testing.assert_close(out, want, rtol=0.0, atol=0.0)
        torch.testing.assert_close(total, (want * want).sum(), rtol=1e-15, atol=0.0)
        expected = torch.nonzero(want > 10.0).squeeze(1)[:4]
        expected = torch.cat([expected, expected.new_full((4 - expected.numel(),), -1)])
        assert torch.equal(rows, expected)
    assert call.captures == (1 if device == "cuda" else 0)
    call.reset()
    out, _, _ = call()
    torch.testing.assert_close(out, 3.0 * x + y, rtol=0.0, atol=0.0)
    assert call.captures == (2 if device == "cuda" else 0)


def test_captured_calls_outlive_graphs_left_to_the_collector(device):
    """Graphs dropped in reference cycles are collected outside later captures (a graph destroyed during a capture
    would void it)."""
    x = torch.arange(4, dtype=torch.float64, device=backend.torch_device())
    for k in range(4):
        holder: dict = {}
        holder["self"] = holder  # a cycle: only the collector frees it
        holder["call"] = backend.CapturedCall(lambda: x * 2.0 + 1.0)
        torch.testing.assert_close(holder["call"](), x * 2.0 + 1.0)
        del holder
        x.add_(k)
