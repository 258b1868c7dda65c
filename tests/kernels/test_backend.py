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
