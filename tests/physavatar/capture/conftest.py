"""The hand-made user capture of :mod:`tests.physavatar.handmade_capture`, shared by this package's tests."""

import pytest

from tests.physavatar.handmade_capture import build_handmade_capture


@pytest.fixture(scope="session")
def handmade(tmp_path_factory):
    """The default hand-made capture with its ``boundary.txt``, built once per session: ``(folder, what the builder
    returned)``; read it, never write into it."""
    folder = tmp_path_factory.mktemp("handmade_boundary")
    return folder, build_handmade_capture(folder, boundary=True)
