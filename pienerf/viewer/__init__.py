"""The interactive drag-and-force viewer (PIE-NeRF Fig. 1, 5): a simulation loop behind browser front ends.

* :mod:`pienerf.viewer.loop`: the :class:`~pienerf.viewer.loop.Viewer` protocol and
  :class:`~pienerf.viewer.loop.DemoApp`, the command queue and simulation loop;
* :mod:`pienerf.viewer.viser_viewer`: the viser front end;
* :mod:`pienerf.viewer.meshcat_viewer` (with :mod:`pienerf.viewer.meshcat_server` and the page in ``web/``): the
  meshcat front end, the default;
* :mod:`pienerf.viewer.nerf_job`: the NeRF render mode's checkpoint, fitted in a separate process;
* :mod:`pienerf.viewer.origin`: address checks, and the request check that refuses foreign ``Host`` and ``Origin``
  headers (inside viser's server too).

:func:`build_app` puts a scene's simulation behind the chosen front end.
"""

from __future__ import annotations

from pienerf.session import Simulation, SimulationConfig
from pienerf.viewer.loop import RENDER_MODES, DemoApp
from pienerf.viewer.nerf_job import load_nerf, smoke_fit
from pienerf.viewer.origin import check_address

__all__ = ["RENDER_MODES", "SMOKE", "VIEWERS", "DemoApp", "build_app"]

SMOKE = {"kernel_count": 6, "particle_radius": 0.06, "lloyd_iterations": 0}
"""Settings of a smoke run: a body of a few kernels that builds in seconds."""

VIEWERS = ("meshcat", "viser")
"""The front ends :func:`build_app` knows."""


def build_app(
    scene: str,
    viewer_name: str,
    host: str,
    port: int,
    smoke: bool,
    render: str = "mesh",
    nerf_checkpoint: str | None = None,
    cache_dir: str | None = None,
    progress=None,
) -> DemoApp:
    """The simulation of ``scene`` behind the chosen viewer, showing ``render`` (:data:`RENDER_MODES`).

    With ``render="nerf"`` the NeRF is loaded from ``nerf_checkpoint`` or fitted to the scene (a few-second fit
    with ``smoke``) before the viewer starts; ``progress(stage, fraction)`` follows the set-up. A bad ``host`` or
    ``port`` raises ValueError, a port in use OSError, before the simulation is built.
    """
    check_address(host, port)  # before the simulation is built
    if viewer_name not in VIEWERS:
        raise ValueError(f"unknown viewer {viewer_name!r}; valid: {', '.join(VIEWERS)}")
    if render not in RENDER_MODES:
        raise ValueError(f"unknown render mode {render!r}; valid: {', '.join(RENDER_MODES)}")
    # The viewer first: a port in use is reported before the simulation is built. The front ends are imported here,
    # deferred: meshcat with tornado, or viser, load only when their front end is built.
    if viewer_name == "viser":
        from pienerf.viewer.viser_viewer import ViserViewer

        viewer = ViserViewer(host, port)
    else:
        from pienerf.viewer.meshcat_viewer import MeshcatViewer

        viewer = MeshcatViewer(host, port)
    try:
        simulation = Simulation(SimulationConfig.create(scene, **(SMOKE if smoke else {})), progress)
        nerf_options = {"checkpoint": nerf_checkpoint, "fit": smoke_fit() if smoke else None, "cache_dir": cache_dir}
        if render == "nerf":
            load_nerf(simulation, progress=progress, **nerf_options)
        return DemoApp(simulation, viewer, render, nerf_options)
    except BaseException:
        viewer.close()
        raise
