"""Shared fixtures.

Taichi holds one architecture per process, so a test process runs its kernels on one device:
``--device`` picks it (default: cuda when present, else cpu). The ``device`` fixture is parametrised
over that choice, so every kernel test runs on CPU here and on CUDA on a GPU machine; run
``pytest --device cpu`` there for the CPU pass.

Markers: ``data`` (touches the shared data folder), ``browser`` (drives chromium) and ``slow`` (seconds to tens of
seconds each): ``pytest -m "not slow"`` is the quick pass for development; the default run, CI's, runs every test.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from kernels import backend
from pienerf.paths import SHARED_DATA


def pytest_addoption(parser):
    parser.addoption(
        "--device",
        default=None,
        choices=list(backend.DEVICES),
        help="device the kernels run on in this test process (default: cuda when present, else cpu)",
    )


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "data: touches the shared data folder (directly or through an app's default); CI runs these once more with "
        "PIE_SHARED_DATA pointing nowhere, as on a machine without the folder",
    )
    config.addinivalue_line(
        "markers",
        "slow: takes seconds to tens of seconds (trains a NeRF, runs a benchmark workload or a long simulation); "
        "`pytest -m 'not slow'` leaves these out for a quick pass, the default run (CI's) keeps them",
    )
    config.addinivalue_line("markers", "browser: drives a real browser (Playwright and Debian's chromium)")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.data)


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        device = metafunc.config.getoption("--device") or backend.default_device()
        metafunc.parametrize("device", [device], indirect=True)


@pytest.fixture
def device(request) -> str:
    """The device of this test process, with Taichi and Warp initialised for it."""
    if request.param not in backend.available_devices():
        pytest.skip(f"device {request.param!r} is not present on this machine")
    return backend.init(request.param)


@pytest.fixture
def shared_data() -> Path:
    """The project's read-only data folder beside the checkout; skips where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent on this machine")
    return SHARED_DATA


@pytest.fixture(scope="module")
def local_ray(request):
    """A Ray of 2 CPUs on 127.0.0.1 for the tests of one module, shut down after them; skips where Ray is not
    installed (the optional extra ``.[cluster]``). The module's own functions travel to the workers by value, as a
    script's do, since the workers do not import the test modules."""
    ray = pytest.importorskip("ray", reason="Ray is not installed: pip install -e '.[cluster]'")
    ray.cloudpickle.register_pickle_by_value(request.module)
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False)
    yield ray
    ray.shutdown()
    ray.cloudpickle.unregister_pickle_by_value(request.module)
