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

import importlib

from pienerf.scenes import SCENES
from pienerf.session import Simulation, SimulationConfig
from pienerf.viewer.loop import (
    CONTROL_RANGES,
    MAX_PENDING_COMMANDS,
    RENDER_MODES,
    REST_FRAMES,
    REST_SPEED,
    CommandQueue,
    DemoApp,
    NerfSchedules,
    Viewer,
    control_value,
    nerf_image,
    number_in,
    picked_text,
    render_nerf_in_budget,
    si_text,
    vector3,
)
from pienerf.viewer.nerf_job import (
    ASSET_DIR,
    FIRST_FIT,
    SHIPPED_NERFS,
    NerfJob,
    build_nerf_asset,
    load_nerf,
    shipped_nerf,
    shipped_nerf_path,
    smoke_fit,
)
from pienerf.viewer.origin import (
    LOOPBACK,
    VISER_VERSIONS,
    RequestCheck,
    allowed_hosts,
    bind_socket,
    check_address,
    checked_viser_server,
)

_FRONT_END_NAMES = {
    "MAX_MESSAGE_BYTES": "meshcat_server",
    "MeshcatServer": "meshcat_server",
    "Y_UP_TO_Z_UP": "meshcat_viewer",
    "MeshcatViewer": "meshcat_viewer",
    "page_cameras": "meshcat_viewer",
    "ViserViewer": "viser_viewer",
}
"""The front ends' names, imported on first use (:func:`__getattr__`): meshcat brings tornado and IPython, viser its
own server; a program that uses neither does not load them."""

__all__ = [
    "ASSET_DIR",
    "CONTROL_RANGES",
    "FIRST_FIT",
    "LOOPBACK",
    "MAX_MESSAGE_BYTES",
    "MAX_PENDING_COMMANDS",
    "RENDER_MODES",
    "REST_FRAMES",
    "REST_SPEED",
    "SHIPPED_NERFS",
    "SMOKE",
    "VIEWERS",
    "VISER_VERSIONS",
    "Y_UP_TO_Z_UP",
    "CommandQueue",
    "DemoApp",
    "MeshcatServer",
    "MeshcatViewer",
    "NerfJob",
    "NerfSchedules",
    "RequestCheck",
    "Viewer",
    "ViserViewer",
    "allowed_hosts",
    "bind_socket",
    "build_app",
    "build_nerf_asset",
    "check_address",
    "checked_viser_server",
    "control_value",
    "load_nerf",
    "nerf_image",
    "number_in",
    "page_cameras",
    "picked_text",
    "render_nerf_in_budget",
    "shipped_nerf",
    "shipped_nerf_path",
    "si_text",
    "smoke_fit",
    "vector3",
]


def __getattr__(name: str):
    """A front end's public name, importing its module on first use (PEP 562)."""
    module = _FRONT_END_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


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
    simulation=None,
    scenes: dict | None = None,
) -> DemoApp:
    """The simulation of ``scene`` behind the chosen viewer, showing ``render`` (:data:`RENDER_MODES`), with a
    scene menu that switches to any embedded scene (:data:`pienerf.scenes.SCENES`) or one of ``scenes``.

    ``scenes`` maps the names of scenes of other packages to their builders, called as ``builder(progress)``: the
    dressed avatar (:class:`physavatar.session.AvatarSimulation`, which this package may not import; ``apps.demo``
    passes it) behind the same verbs. ``simulation``, when given, builds ``scene`` that way (the same as
    ``scenes={scene: simulation}``). A ``scene`` that is a mesh or checkpoint path joins the menu too.

    With ``render="nerf"`` the NeRF is loaded from ``nerf_checkpoint`` or fitted to the scene (a few-second fit
    with ``smoke``) before the viewer starts; ``progress(stage, fraction)`` follows the set-up. A bad ``host`` or
    ``port`` raises ValueError, a port in use OSError, before the simulation is built.
    """
    check_address(host, port)  # before the simulation is built
    if viewer_name not in VIEWERS:
        raise ValueError(f"unknown viewer {viewer_name!r}; valid: {', '.join(VIEWERS)}")
    if render not in RENDER_MODES:
        raise ValueError(f"unknown render mode {render!r}; valid: {', '.join(RENDER_MODES)}")
    others = dict(scenes or {})
    if simulation is not None:
        others[scene] = simulation
    names = tuple(dict.fromkeys((*SCENES, *others, scene)))

    def build_scene(name: str, progress=None):
        if name in others:
            return others[name](progress)
        return Simulation(SimulationConfig.create(name, **(SMOKE if smoke else {})), progress)

    # The viewer first: a port in use is reported before the simulation is built. The front end's module loads
    # here (meshcat with tornado, or viser), only when that front end is built.
    viewer = __getattr__("ViserViewer" if viewer_name == "viser" else "MeshcatViewer")(host, port)
    menu = {"scene": scene, "scenes": names, "build_scene": build_scene}
    nerf_options = {"checkpoint": nerf_checkpoint, "fit": smoke_fit() if smoke else None, "cache_dir": cache_dir}
    try:
        if scene in others:
            if render != "mesh":
                raise ValueError(f"the {scene} scene shows its mesh only, got --render {render}")
            return DemoApp(others[scene](progress), viewer, render, nerf_options, **menu)
        simulation = build_scene(scene, progress)
        if render == "nerf":
            load_nerf(simulation, progress=progress, **nerf_options)
        return DemoApp(simulation, viewer, render, nerf_options, **menu)
    except BaseException:
        viewer.close()
        raise
