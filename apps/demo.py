"""Interactive drag-and-force viewer of a Q-GMLS body (PIE-NeRF Fig. 1, 5).

    python -m apps.demo [--scene plant|teapot|jelly|cloth|sculpture|avatar|PATH] [--device cpu|cuda]
                        [--host 127.0.0.1] [--port 8080] [--viewer meshcat|viser] [--smoke]
                        [--render mesh|particles|nerf] [--nerf-checkpoint PATH] [--cache-dir DIR]
                        [--frame-budget-ms 33.3] [--garment NAME|PATH] [--motion walk|turn|raise|jump|BVH]
                        [--capture FOLDER]
    python -m apps.demo --build-nerf-asset

``--build-nerf-asset`` fits the plant's coarse NeRF again with the project's own fitting code and writes the copy
that ships in ``assets/nerf/`` (:func:`pienerf.viewer.nerf_job.build_nerf_asset`; float16 weights, under 1 MB); run
it after a change to the plant, to the viewer's first fit or to the fitting recipe (the file's name holds the fit's
digest, so a stale copy is never loaded for other settings).

``meshcat`` (default) serves meshcat's own three.js client under a page of the project
(:class:`pienerf.viewer.meshcat_viewer.MeshcatViewer`): the deformed scene mesh updated every frame, a panel with the
material (Young's modulus, Poisson ratio, density, model), damping, gravity, the kernel count (re-sampling shows
progress), pin / push / cut / release / reset buttons, the render mode, the frame rate, the time breakdown and the
last message. Press on the body and drag: the press picks a material point and the pointer's ray, at the picked
depth, is the drag target until release; a click (no move) keeps the point picked for pin / push / cut. ``viser``
serves the same panel through viser, with the particles and the integrator points as toggles; a click picks, a
further click moves the target onto that ray at the picked depth, and a gizmo at the target moves it in 3-D. The
spring of :class:`pienerf.sim.picking.DragController` pulls the body. ``--smoke`` starts the viewer, runs a few steps
headless and exits 0.

``--render`` picks what the page shows (the panel's "render" menu switches it later): ``mesh`` (default) and
``particles`` are drawn by the browser; ``nerf`` is a NeRF of the scene warped by the body's deformation (quadratic
ray warping, PIE-NeRF Eq. 19–21), rendered on the server from each client's camera and shown as the page's
background image with its depth. While the body or the camera moves it is rendered as coarse as needed for the step
and the render to fit in ``--frame-budget-ms`` (default 33.3 ms, 30 frames/s; the resolution adapts to the measured
render time, starting at a quarter), then once at full resolution when still. The NeRF is trained on the scene's own
rendered views the first time, with progress in the terminal (or, when switched on in the panel, in a separate
process while the simulation goes on, with progress in the panel), and cached as a checkpoint under the scene cache
(``--cache-dir``, default ``$PIE_CACHE_DIR`` or ``~/.cache/pie-physavatar``), so later starts load it;
``--nerf-checkpoint`` loads a given one instead (trained in the scene's coordinates). For the plant
the NeRF ships with the project (``assets/nerf/``) and shows at once, while the default fit refines it in the
background; for the other scenes the first fit takes longer than a start may take on a CPU (figures in
``docs/benchmarks.md``), so the default stays ``mesh``; later starts load the cached checkpoint. In viser's NeRF
mode the body is picked by clicking (the mouse-drag handle belongs to the hidden mesh).

``--scene avatar`` dresses the procedural mannequin in a garment (:class:`physavatar.session.AvatarSimulation`):
the mannequin plays a motion (``--motion``: walk, turn, raise, jump or a BVH file; each loops) and the garment
is simulated by PhysAvatar's Codim-IPC cloth solver, one implicit step a frame. The panel plays, pauses and
scrubs the motion and sets its speed; sets the fabric (density, κs, κb, friction) or a preset (silk, cotton,
denim, leather, :data:`physavatar.session.FABRIC_PRESETS`); and shows the contact: garment vertices within the
barrier's reach of the body tinted, the smallest distances to the body and to itself, and the count of vertices
inside the body (0: the barrier keeps them out). The garment is dragged as the bodies are (a clamped spring on
the picked vertex, a term of the step's potential) and a clicked vertex can be pinned. ``--garment`` picks it:
``procedural``, a shared garment's name (``skirt1252``, ``skirt7271``) or an OBJ/PLY path; by default the full
``skirt7271`` on CUDA and, on the CPU, a procedural skirt small enough to stay interactive (the page says which,
and so does the terminal before a page connects).

``--capture FOLDER`` puts the garment on a user's capture (``docs/capture.md``) instead of the mannequin: the body
sequence of its meshes (read as ``apps.avatar``'s stages read it, no image opened), resampled to 25 frames/s and
played forward then back so that it loops, wearing the capture's garment, or ``--garment PATH`` (an OBJ/PLY worn by
the capture's body at its first frame, in its axes). The garment's intersections with the body are resolved as the
``prepare`` stage resolves them. A folder that is not a capture is refused with what is wrong and how to fix it.

The panel's scene menu switches the scene without a restart, to and from the avatar: the chosen scene is built (with
progress in the panel) while the current one waits, then shown in its place; an unknown name is refused and a scene
that fails to build leaves the current one, with the error in the panel. ``--garment``, ``--motion`` and
``--capture`` dress the avatar whenever it is chosen.

The viewer lives in :mod:`pienerf.viewer`: events become commands queued to the simulation loop, which runs them
between steps; a command that fails (a malformed message, a bad value) is reported in the panel and the loop goes
on, and a client that disconnects only leaves its GUI behind. A bad ``--host`` or ``--port`` (outside 0..65535) is
refused before anything starts; a port in use stops the start with a message naming it. This program parses the
flags and starts it.
"""

from __future__ import annotations

import argparse
import math
import sys

from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

from kernels import backend
from physavatar.session import AVATAR_MOTIONS, AvatarConfig, AvatarSimulation
from pienerf.nerf.cameras import orbit_cameras
from pienerf.viewer import RENDER_MODES, VIEWERS, build_app
from pienerf.viewer.nerf_job import build_nerf_asset
from pienerf.viewer.origin import check_address


class _TerminalProgress:
    """A rich progress bar for the start-up, called as ``progress(stage, fraction)``."""

    def __enter__(self):
        self.bar = Progress(
            BarColumn(), TaskProgressColumn(), TimeElapsedColumn(), TextColumn("{task.description}"), transient=True
        )
        self.task = self.bar.add_task("starting", total=1.0)
        self.bar.start()
        return self

    def __call__(self, stage: str, fraction: float) -> None:
        self.bar.update(self.task, completed=fraction, description=stage)

    def __exit__(self, *exc) -> None:
        self.bar.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scene",
        default="plant",
        help="plant, teapot, jelly, cloth, sculpture, avatar (the dressed mannequin), a mesh path or a NeRF "
        "checkpoint (.pt)",
    )
    parser.add_argument(
        "--garment",
        default=None,
        help="avatar scene: procedural, a shared garment (skirt1252, skirt7271) or an OBJ/PLY path (default: "
        "skirt7271 on CUDA, a small procedural skirt on the CPU)",
    )
    parser.add_argument(
        "--motion",
        default=None,
        help=f"avatar scene: the motion at start, {', '.join(AVATAR_MOTIONS)} (default walk) or a .bvh file "
        "(retargeted, looped)",
    )
    parser.add_argument(
        "--capture",
        default=None,
        help="avatar scene: a capture folder (docs/capture.md) whose body sequence the garment is simulated on "
        "(its own garment unless --garment PATH)",
    )
    parser.add_argument("--device", choices=list(backend.DEVICES), default=None)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8080, help="TCP port, 0..65535 (0 picks a free one)")
    parser.add_argument("--viewer", choices=VIEWERS, default="meshcat")
    parser.add_argument("--smoke", action="store_true", help="start, run a few steps headless, exit")
    parser.add_argument(
        "--render",
        choices=RENDER_MODES,
        default="mesh",
        help="what the page shows first (the panel switches it): browser mesh, particles, or the "
        "server's warped-NeRF image (trains the scene's NeRF on first use)",
    )
    parser.add_argument("--nerf-checkpoint", default=None, help="a trained NeRF checkpoint to render instead")
    parser.add_argument("--cache-dir", default=None, help="cache of scene renders and NeRF checkpoints")
    parser.add_argument(
        "--frame-budget-ms",
        type=float,
        default=1e3 / 30.0,
        help="milliseconds a NeRF frame may take while things move, step and render together (its resolution "
        "adapts to hold it)",
    )
    parser.add_argument(
        "--build-nerf-asset",
        action="store_true",
        help="fit the plant's coarse NeRF and write the copy shipped in assets/nerf/, then exit",
    )
    args = parser.parse_args(argv)
    if args.build_nerf_asset:
        backend.init(args.device)
        with _TerminalProgress() as progress:
            path = build_nerf_asset("plant", progress=progress)
        print(f"wrote {path}")
        return 0
    try:
        check_address(args.host, args.port)
    except ValueError as error:
        parser.error(str(error))
    if not 0.0 < args.frame_budget_ms < math.inf:
        parser.error(
            f"--frame-budget-ms must be a positive number of milliseconds (33.3: 30 frames/s), "
            f"got {args.frame_budget_ms}"
        )
    if args.capture is not None and args.motion is not None:
        parser.error("--motion and --capture exclude each other: a capture plays its own body sequence")
    smoke_garment = args.smoke and args.garment is None and args.capture is None
    try:
        config = AvatarConfig(
            garment="procedural" if smoke_garment else args.garment, motion=args.motion or "walk", capture=args.capture
        )
    except ValueError as error:
        parser.error(str(error))
    backend.init(args.device)
    avatar = lambda progress: AvatarSimulation(config, progress)  # noqa: E731
    try:
        with _TerminalProgress() as progress:
            app = build_app(
                args.scene,
                args.viewer,
                args.host,
                args.port,
                args.smoke,
                args.render,
                args.nerf_checkpoint,
                args.cache_dir,
                progress,
                scenes={"avatar": avatar},
            )
    except (ValueError, OSError) as error:  # a bad scene or value, a missing file, a port in use
        print(f"error: {error.strerror if isinstance(error, OSError) and error.strerror else error}", file=sys.stderr)
        return 2
    app.viewer.nerf_schedules.frame_budget = args.frame_budget_ms / 1e3
    if args.smoke:
        app.run(steps=3)
        app.close()
        print(f"smoke: 3 steps of {args.scene}, t = {app.simulation.time:.3f} s")
        if args.render != "mesh":
            sim = app.simulation
            cameras = orbit_cameras(sim.centre, 2.6, [30.0], 15.0, 64, 48)
            frame = sim.render(cameras, 0, "nerf" if args.render == "nerf" else "particles")
            coverage = float((frame.rgba[..., 3] > 0.5).float().mean())
            print(f"smoke: {args.render} frame 64x48, {100 * coverage:.0f} % covered")
        return 0
    url = getattr(app.viewer, "url", None) or f"http://{args.host}:{app.viewer.port}"
    print(f"viewer at {url}; Ctrl+C stops")
    try:
        app.run()
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
