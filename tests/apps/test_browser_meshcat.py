"""End to end in a real browser: the meshcat page drags the body, changes the material, pins, resets and shows
the NeRF render; prints the page's frame rates (not asserted: speed is the benchmark suite's job). At the demo's
own size (not the smoke plant) a press on a leaf and a sideways drag must pull the leaf and show it move.

Needs Debian's ``chromium`` (``apt-get install -y chromium``) and the ``playwright`` package. Skipped when
chromium is absent, unless the environment variable CI is set: then it must run.
"""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
import torch
from PIL import Image

from pienerf.viewer import build_app
from tests.apps import chromium
from tests.apps.chromium import requires_chromium
from tests.pienerf.viewer.test_loop import free_port

pytestmark = pytest.mark.browser

WIDTH, HEIGHT = 1280, 800

# A pixel whose ray hits the plant's mesh above the pot, found with the page's own camera and raycaster.
_FIND_BODY_PIXEL = """() => {
    const {viewer} = window.pienerf;
    const THREE = MeshCat.THREE;
    const body = viewer.scene_tree.find(["pienerf", "body", "<object>"]).object;
    const root = viewer.scene_tree.find(["pienerf"]).object;
    const toScene = new THREE.Matrix4().copy(root.matrixWorld).invert();
    const rect = viewer.renderer.domElement.getBoundingClientRect();
    const raycaster = new THREE.Raycaster();
    viewer.camera.updateMatrixWorld();
    for (let dy = 0; dy < 300; dy += 10) {
        for (const dx of [0, 10, -10, 20, -20, 40, -40]) {
            const x = rect.width / 2 + dx, y = rect.height / 2 - dy;
            raycaster.setFromCamera(new THREE.Vector2(2 * x / rect.width - 1, 1 - 2 * y / rect.height), viewer.camera);
            const hits = raycaster.intersectObject(body, false);
            if (hits.length && hits[0].point.clone().applyMatrix4(toScene).y > 0.55) return [x, y];
        }
    }
    return null;
}"""


def _poll(page, app, condition, seconds: float = 15.0) -> bool:
    """Run the simulation loop in this (the main) thread, as the demo does, and let the page work, until
    ``condition`` holds or ``seconds`` pass."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        app.tick()
        if condition():
            return True
        page.wait_for_timeout(10)
    return condition()


def _open_page(playwright, app, width: int, height: int):
    """``(browser, page)``: the viewer's page in headless chromium at ``width × height``, once it has the body."""
    browser = chromium.launch(playwright)
    page = browser.new_page(viewport={"width": width, "height": height})
    page.goto(app.viewer.url)
    loaded = lambda: page.evaluate("() => window.pienerf !== undefined && window.pienerf.stats.updates > 2")  # noqa: E731
    assert _poll(page, app, loaded, 60.0), "the page did not receive the body"
    return browser, page


def _stats(page) -> dict:
    return page.evaluate("() => ({...window.pienerf.stats, controls: null})")


def _region(page, x: float, y: float, size: int = 120) -> np.ndarray:
    clip = {"x": x - size / 2, "y": y - size / 2, "width": size, "height": size}
    return np.asarray(Image.open(io.BytesIO(page.screenshot(clip=clip))).convert("RGB"), dtype=np.float32)


def _rates(page, app, label: str) -> None:
    _poll(page, app, lambda: False, 2.1)  # two of the page's one-second counting windows
    s = _stats(page)
    print(
        f"\nmeshcat page, {label}: {s['rafPerSecond']:.0f} animation frames/s, {s['rendersPerSecond']:.0f} renders/s, "
        f"{s['updatesPerSecond']:.0f} body updates/s ({s['updateMilliseconds']:.2f} ms each), "
        f"{s['nerfImages']} NeRF images so far"
    )


@requires_chromium
def test_meshcat_page_drags_sets_pins_resets_and_shows_the_nerf(device, tmp_path):
    from playwright.sync_api import sync_playwright

    app = build_app("plant", "meshcat", "127.0.0.1", free_port(), smoke=True, cache_dir=str(tmp_path))
    sim = app.simulation
    drag = sim.interaction.drag
    default_pins = len(sim.interaction.pins)
    try:
        with sync_playwright() as playwright:
            browser, page = _open_page(playwright, app, WIDTH, HEIGHT)
            panel = page.evaluate("() => document.getElementById('panel').getBoundingClientRect().bottom")
            assert panel <= HEIGHT, f"the panel ends at {panel} px, below the {HEIGHT} px window"
            assert page.evaluate("() => document.scrollingElement.scrollHeight") <= HEIGHT
            _rates(page, app, "mesh mode, body at rest")

            pixel = page.evaluate(_FIND_BODY_PIXEL)
            assert pixel is not None, "no pixel near the middle of the view shows the plant above its pot"
            x, y = pixel

            # Drag: press on the body, move right; the body follows in Python and on the page.
            before = _region(page, x, y)
            page.mouse.move(x, y)
            page.mouse.down()
            assert _poll(page, app, lambda: drag.dragging), f"the press did not pick: errors {app.errors}"
            start = drag.hit.world.clone()
            page.mouse.move(x + 150, y, steps=15)
            moved = lambda: float(drag.position(sim.state.q)[0] - start[0]) > 0.03  # noqa: E731
            assert _poll(page, app, lambda: drag.dragging and moved()), (
                f"picked {drag.hit}, target {drag.target}, t = {sim.time:.2f} s, errors {app.errors}"
            )
            _rates(page, app, "mesh mode, while dragging")
            during = _region(page, x, y)
            changed = float(np.abs(during - before).mean())
            assert changed > 2.0, f"the page's pixels around the body barely changed ({changed:.2f} / 255)"
            page.mouse.up()
            assert _poll(page, app, lambda: not drag.dragging), "the release did not reach the server"

            # Young's modulus: the slider's keyboard steps reach the solver, the label reads in pascals.
            young = sim.material.young_modulus
            page.focus("#young_modulus")
            for _ in range(4):
                page.keyboard.press("ArrowRight")
            assert _poll(page, app, lambda: sim.material.young_modulus > 1.2 * young), f"errors {app.errors}"
            assert "MPa" in page.inner_text("#young_modulus-value")
            assert _poll(page, app, lambda: "young modulus" in _stats(page)["lastMessage"])

            # A click keeps a point picked; pin it; reset. The plant still swings from the drag, so a click may land
            # where it was a frame earlier, off the body: then it is clicked again where it is now.
            for _ in range(3):
                pixel = page.evaluate(_FIND_BODY_PIXEL)  # where the swinging plant is now
                assert pixel is not None, "the plant left the middle of the view"
                page.mouse.click(*pixel)
                if _poll(page, app, lambda: drag.dragging, 5.0):
                    break
            assert drag.dragging, f"the click did not pick: errors {app.errors}"
            page.click("#pin")
            assert _poll(page, app, lambda: len(sim.interaction.pins) == default_pins + 1), f"errors {app.errors}"
            page.click("#reset")
            assert _poll(page, app, lambda: len(sim.interaction.pins) == default_pins and not drag.dragging)

            # The NeRF mode: the smoke fit, then images rendered from the page's camera.
            page.select_option("#render_mode", "nerf")
            assert _poll(page, app, lambda: _stats(page)["nerfImages"] > 0, 240.0), f"errors {app.errors}"
            assert app.render_mode == "nerf" and app.viewer.last_nerf_image is not None
            shown = "() => { const n = document.getElementById('nerf'); return !n.hidden && n.naturalWidth > 0; }"
            assert page.evaluate(shown), "the NeRF image is not shown"
            _rates(page, app, "NeRF mode")
            browser.close()
        assert app.errors == []
    finally:
        app.viewer.close()


# The pixel of a leaf of the plant: the body pixel (away from the mesh's edges) whose hit lies farthest from the
# stem's axis, above the pot; with the screen x of the axis at that height, so a drag can pull the leaf outward.
_FIND_LEAF_PIXEL = """([axisX, axisZ]) => {
    const {viewer} = window.pienerf;
    const THREE = MeshCat.THREE;
    const body = viewer.scene_tree.find(["pienerf", "body", "<object>"]).object;
    const root = viewer.scene_tree.find(["pienerf"]).object;
    const toScene = new THREE.Matrix4().copy(root.matrixWorld).invert();
    const rect = viewer.renderer.domElement.getBoundingClientRect();
    const raycaster = new THREE.Raycaster();
    viewer.camera.updateMatrixWorld();
    const hit = (x, y) => {
        raycaster.setFromCamera(new THREE.Vector2(2 * x / rect.width - 1, 1 - 2 * y / rect.height), viewer.camera);
        const hits = raycaster.intersectObject(body, false);
        return hits.length ? hits[0].point.clone().applyMatrix4(toScene) : null;
    };
    let best = null;
    for (let y = 0; y < rect.height; y += 6) {
        for (let x = 0; x < rect.width; x += 6) {
            const point = hit(x, y);
            if (point === null || point.y < 0.4) continue;
            if (![[4, 0], [-4, 0], [0, 4], [0, -4]].every(([dx, dy]) => hit(x + dx, y + dy) !== null)) continue;
            const radial = Math.hypot(point.x - axisX, point.z - axisZ);
            if (best === null || radial > best.radial) best = {x, y, radial, height: point.y};
        }
    }
    if (best === null) return null;
    const axis = new THREE.Vector3(axisX, best.height, axisZ).applyMatrix4(root.matrixWorld).project(viewer.camera);
    return [best.x, best.y, (axis.x + 1) / 2 * rect.width];
}"""

_SET_VISIBLE = """([path, visible]) => {
    const {viewer} = window.pienerf;
    viewer.scene_tree.find(path.concat(["<object>"])).object.visible = visible;
    viewer.set_dirty();
}"""


def _wait_for_updates(page, seen: int, seconds: float = 10.0) -> None:
    """Let the page take in the body updates sent after it had counted ``seen``, until they stop coming."""
    deadline, last = time.monotonic() + seconds, seen
    while time.monotonic() < deadline:
        page.wait_for_timeout(300)
        count = _stats(page)["updates"]
        if seen < count == last:
            return
        last = count
    raise AssertionError(f"the page took in {last - seen} body updates and kept changing for {seconds} s")


def _screen(page) -> np.ndarray:
    """``[H, W, 3]`` the whole page, after the page has drawn what it was last sent."""
    page.evaluate("() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")
    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), dtype=np.float32)


@requires_chromium
def test_meshcat_page_drags_a_leaf_of_the_default_plant(device):
    """The demo's first minute at its own size: the plant stands, a press on a leaf and a sideways drag pull the
    leaf half way to the pointer within 0.5 s of simulated time, and the page shows it move."""
    from playwright.sync_api import sync_playwright

    app = build_app("plant", "meshcat", "127.0.0.1", free_port(), smoke=False)
    sim = app.simulation
    drag = sim.interaction.drag
    centre = sim.centre.double()
    try:
        with sync_playwright() as playwright:
            browser, page = _open_page(playwright, app, WIDTH, HEIGHT)
            # the page may not have drawn the plant yet when it opens: look until it has (the loop running meanwhile)
            leaf = lambda: page.evaluate(_FIND_LEAF_PIXEL, [float(centre[0]), float(centre[2])])  # noqa: E731
            drawn = _poll(page, app, lambda: leaf() is not None, 5.0)
            assert drawn, "no pixel of the view shows the plant above its pot"
            found = leaf()
            x, y, axis_x = found
            outward = 1.0 if x > axis_x else -1.0
            before = _screen(page)

            # Press on the leaf, move the pointer 80 px outward; the loop only runs commands until the last
            # pointer ray has arrived, so the 0.5 s of simulated time start with the final target.
            page.mouse.move(x, y)
            page.mouse.down()
            assert _poll(page, app, lambda: drag.dragging), f"the press did not pick: errors {app.errors}"
            start = drag.position(sim.state.q).cpu().clone()
            sag = float((start - drag.hit.rest).norm())
            assert sag < 0.05, f"the leaf hangs {sag:.3f} m below where it rests: the plant does not stand"
            page.mouse.move(x + outward * 80, y, steps=8)
            targets, deadline = [drag.target.clone()], time.monotonic() + 10.0
            arrived = lambda: float((targets[-1] - start).norm()) > 0.05 and torch.equal(targets[-1], targets[-20])  # noqa: E731
            while time.monotonic() < deadline and not (len(targets) >= 20 and arrived()):
                app.run_commands()
                targets.append(drag.target.clone())
                page.wait_for_timeout(10)
            pull = targets[-1] - start
            assert float(pull.norm()) > 0.05, f"the drag target moved only {float(pull.norm()):.3f} m: {app.errors}"
            began, updates = sim.time, _stats(page)["updates"]
            for _ in range(round(0.5 / sim.config.dt)):
                app.tick()
            assert sim.time == pytest.approx(began + 0.5, abs=1e-6)
            covered = float((drag.position(sim.state.q).cpu() - start) @ pull) / float(pull @ pull)
            assert covered >= 0.5, f"the leaf covered {covered:.2f} of a {float(pull.norm()):.3f} m drag in 0.5 s"

            # The page: the body's silhouette (pixels unlike the same view without the body) near the leaf.
            _wait_for_updates(page, updates)
            page.evaluate(_SET_VISIBLE, [["pienerf", "drag_target"], False])
            after = _screen(page)
            page.evaluate(_SET_VISIBLE, [["pienerf", "body"], False])
            empty = _screen(page)
            panel = page.evaluate(
                "() => { const r = document.getElementById('panel').getBoundingClientRect(); "
                "return [r.left, r.top, r.right, r.bottom]; }"
            )
            page.mouse.up()
            browser.close()
        for image in (before, after, empty):  # the panel's text changes; only the 3-D view counts
            image[int(panel[1]) : int(panel[3]) + 1, int(panel[0]) : int(panel[2]) + 1] = 0.0
        window = (
            slice(max(0, int(y) - 150), int(y) + 150),
            slice(max(0, int(min(x, x + outward * 80)) - 150), int(max(x, x + outward * 80)) + 150),
        )
        shown = [np.abs(image - empty).max(-1)[window] > 40 for image in (before, after)]
        iou = float((shown[0] & shown[1]).sum() / max((shown[0] | shown[1]).sum(), 1))
        print(f"\nleaf covered {covered:.2f} of {float(pull.norm()):.3f} m; silhouette IoU near the leaf {iou:.2f}")
        assert shown[0].sum() > 500, "the body hardly shows near the leaf before the drag"
        assert iou < 0.9, f"the page barely shows the leaf move: silhouette IoU {iou:.2f} before / after the drag"
        assert app.errors == []
    finally:
        app.viewer.close()


@requires_chromium
def test_meshcat_page_folds_its_controls_in_a_small_window(device, tmp_path):
    """At 640 × 480 the panel starts with its controls folded, so the middle of the view is the scene's; a press on
    the toggle unfolds them."""
    from playwright.sync_api import sync_playwright

    app = build_app("plant", "meshcat", "127.0.0.1", free_port(), smoke=True, cache_dir=str(tmp_path))
    try:
        with sync_playwright() as playwright:
            browser, page = _open_page(playwright, app, 640, 480)
            box = page.evaluate("() => document.getElementById('panel').getBoundingClientRect().toJSON()")
            assert box["bottom"] < 160, f"the folded panel reaches {box['bottom']} px down the 480 px window"
            assert page.evaluate("() => document.elementFromPoint(320, 240).tagName") == "CANVAS"
            assert not page.is_visible("#young_modulus")
            page.click("#collapse")
            assert page.is_visible("#young_modulus") and page.inner_text("#collapse") == "hide controls"
            browser.close()
        assert app.errors == []
    finally:
        app.viewer.close()
