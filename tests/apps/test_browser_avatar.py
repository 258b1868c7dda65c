"""End to end in a real browser: the meshcat page of the dressed avatar (``apps.demo --scene avatar``) pauses and
resumes the walk, drags the skirt's hem sideways and sees it follow with no vertex inside the body, and changes κb
through its slider, which changes how the dragged hem hangs; then switches to the plant and back through the scene
menu. Writes a screenshot of the page while dragging.

At the session's CPU size (the procedural skirt of 96 vertices). Needs Debian's ``chromium`` and the
``playwright`` package; skipped when chromium is absent, unless the environment variable CI is set.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from physavatar.session import AvatarConfig, AvatarSimulation
from pienerf.viewer import build_app
from tests.apps import chromium
from tests.apps.chromium import requires_chromium
from tests.apps.test_browser_meshcat import _poll
from tests.pienerf.viewer.test_loop import free_port

pytestmark = pytest.mark.browser

WIDTH, HEIGHT = 1280, 800
DRAG_PIXELS = 60  # about 0.18 m sideways at the page's camera distance

# A pixel whose ray hits the skirt's front within 3 cm of its hem, found with the page's own camera and raycaster.
_FIND_HEM_PIXEL = """() => {
    const {viewer} = window.pienerf;
    const THREE = MeshCat.THREE;
    const skirt = viewer.scene_tree.find(["pienerf", "body", "<object>"]).object;
    const root = viewer.scene_tree.find(["pienerf"]).object;
    root.updateMatrixWorld(true);
    const toScene = new THREE.Matrix4().copy(root.matrixWorld).invert();
    const positions = skirt.geometry.attributes.position.array;
    let lowest = Infinity;
    for (let i = 1; i < positions.length; i += 3) lowest = Math.min(lowest, positions[i]);
    const rect = viewer.renderer.domElement.getBoundingClientRect();
    const raycaster = new THREE.Raycaster();
    viewer.camera.updateMatrixWorld();
    let best = null;
    for (let y = rect.height / 2; y < rect.height; y += 4) {
        for (const dx of [0, 8, -8, 16, -16]) {
            const x = rect.width / 2 + dx;
            raycaster.setFromCamera(new THREE.Vector2(2 * x / rect.width - 1, 1 - 2 * y / rect.height), viewer.camera);
            const hits = raycaster.intersectObject(skirt, false);
            if (!hits.length) continue;
            const point = hits[0].point.clone().applyMatrix4(toScene);
            if (point.y < lowest + 0.03 && (best === null || point.y < best[2])) best = [x, y, point.y];
        }
    }
    return best;
}"""


def _avatar(progress):
    return AvatarSimulation(AvatarConfig(garment="procedural"), progress)


def _click(page, app, selector: str, done) -> None:
    page.click(selector)
    assert _poll(page, app, done), f"{selector} did not reach the simulation: errors {app.errors}"


def _drag_hem(page, app, pixel, screenshot=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Press on the hem, move the pointer sideways, hold it: ``(x [V, 3] 0.5 s after the target settled, [2] the
    picked vertex's path along the drag and the drag's length, m)``; ``screenshot``, when given, is the file the page
    is captured into before the release."""
    sim = app.simulation
    x, y = pixel
    page.mouse.move(x, y)
    page.mouse.down()
    assert _poll(page, app, lambda: sim.dragging), f"the press did not pick the skirt: errors {app.errors}"
    vertex = sim.drag.hit.vertex
    start = sim.state.x[vertex].cpu().clone()
    page.mouse.move(x + DRAG_PIXELS, y, steps=6)
    # the target settles once the last pointer ray has been run
    last = [None]

    def settled() -> bool:
        target, previous = sim.drag_target.clone(), last[0]
        last[0] = target
        return previous is not None and bool(torch.equal(previous, target)) and float(target[0] - start[0]) > 0.05

    assert _poll(page, app, settled), f"the drag target did not settle: target {sim.drag_target}, start {start}"
    target = last[0]
    clock = sim.time
    while sim.time < clock + 0.5 - 1e-9:  # 0.5 s simulated
        app.tick()
    path = (sim.state.x[vertex].cpu() - start) @ (target - start) / float((target - start).norm())
    if screenshot is not None:
        _poll(page, app, lambda: False, 0.3)  # the page draws the last frames
        page.screenshot(path=str(screenshot))
    page.mouse.up()
    assert _poll(page, app, lambda: not sim.dragging), "the release did not reach the server"
    return sim.state.x.cpu().clone(), torch.stack([path, (target - start).norm()])


@requires_chromium
def test_meshcat_page_pauses_the_walk_drags_the_hem_and_sets_the_bending(device, tmp_path):
    from playwright.sync_api import sync_playwright

    app = build_app("avatar", "meshcat", "127.0.0.1", free_port(), smoke=True, simulation=_avatar)
    sim = app.simulation
    inside: list[int] = []  # vertices inside the body after every step
    step = sim.step

    def counted_step(count: int = 1):
        report = step(count)
        inside.append(sim.contact()["inside"])
        return report

    sim.step = counted_step
    try:
        with sync_playwright() as playwright:
            browser = chromium.launch(playwright)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(app.viewer.url)
            loaded = lambda: page.evaluate("() => window.pienerf !== undefined && window.pienerf.stats.updates > 4")  # noqa: E731
            assert _poll(page, app, loaded, 60.0), "the page did not receive the garment"
            assert page.is_visible("#garment-panel") and not page.is_visible("#young_modulus")

            # Pause: the body holds its frame while the loop steps on; play: it walks again.
            _click(page, app, "#pause", lambda: not sim.playing)
            held = sim.frame
            for _ in range(4):
                app.tick()
            assert sim.frame == held, "the paused walk moved"
            _click(page, app, "#play", lambda: sim.playing and sim.frame > held)
            assert "paused" not in page.inner_text("#status") or _poll(
                page, app, lambda: "paused" not in page.inner_text("#status")
            )

            # The hem follows a sideways drag: half the way within 0.5 s simulated, nothing inside the body.
            hem_ring = sim.mesh_vertices[:, 1] <= sim.mesh_vertices[:, 1].min() + 1e-6
            shapes = []
            for kappa_b in (1.0, None):
                assert sim.time > 0.1
                _click(page, app, "#reset", lambda: sim.time < 0.1)  # a reset and at most two steps
                _click(page, app, "#pause", lambda: not sim.playing)
                _poll(page, app, lambda: False, 0.5)  # the page shows the garment at rest
                pixel = page.evaluate(_FIND_HEM_PIXEL)
                assert pixel is not None, "no pixel near the middle of the view shows the skirt's hem"
                # PIE_SCREENSHOTS=DIR keeps the picture (docs/images/avatar_viewer.png is one, shown by the README)
                shots = Path(os.environ.get("PIE_SCREENSHOTS", tmp_path))
                screenshot = shots / "avatar_viewer.png" if kappa_b is not None else None
                x, path = _drag_hem(page, app, pixel[:2], screenshot)
                assert float(path[0]) >= 0.5 * float(path[1]), f"the hem followed {path[0]:.3f} m of {path[1]:.3f} m"
                shapes.append(x)
                if kappa_b is not None:
                    assert sim.fabric.kappa_b == kappa_b
                    # κb up by the slider's keyboard steps (log scale, 0.05 a step): ×8 in 18 steps
                    page.focus("#kappa_b")
                    for _ in range(18):
                        page.keyboard.press("ArrowRight")
                    assert _poll(page, app, lambda: sim.fabric.kappa_b > 7.0), f"errors {app.errors}"
                    assert sim.solver.config.kappa_b == sim.fabric.kappa_b
            moved = float((shapes[0] - shapes[1])[hem_ring].norm(dim=1).max())
            assert moved > 0.01, f"eight times the bending stiffness moved the dragged hem by {1e3 * moved:.1f} mm"
            assert len(inside) > 50 and max(inside) == 0, f"{max(inside)} garment vertices went inside the body"
            assert "inside the body" in page.inner_text("#contact")
            assert page.title() == page.inner_text("#title") == "PhysAvatar garment drag-and-force demo"
            assert "failed" not in " ".join(app.errors), app.errors
            picture = shots / "avatar_viewer.png"
            print(f"\navatar page: hem ring moved {1e3 * moved:.0f} mm by κb ×8; screenshot {picture}")

            # The scene menu: to the plant and back to the avatar, without a restart.
            page.select_option("#scene", "plant")
            assert _poll(page, app, lambda: app.scene == "plant", 60.0), f"errors {app.errors}"
            assert _poll(page, app, lambda: page.is_visible("#young_modulus") and not page.is_visible("#garment-panel"))
            assert page.title() == "PIE-NeRF drag-and-force demo"
            page.select_option("#scene", "avatar")
            assert _poll(page, app, lambda: app.scene == "avatar", 60.0), f"errors {app.errors}"
            garment_shown = lambda: page.is_visible("#garment-panel") and page.input_value("#scene") == "avatar"  # noqa: E731
            assert _poll(page, app, garment_shown)
            assert app.simulation is not sim and "failed" not in " ".join(app.errors), app.errors
            browser.close()
    finally:
        app.close()
