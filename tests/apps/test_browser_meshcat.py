"""End to end in a real browser: the meshcat page drags the body, changes the material, pins, resets and shows
the NeRF render; prints the page's frame rates (not asserted: speed is the benchmark suite's job).

Needs Debian's ``chromium`` (``apt-get install -y chromium``) and the ``playwright`` package. Skipped when
chromium is absent, unless the environment variable CI is set: then it must run.
"""

from __future__ import annotations

import io
import os
import shutil
import time

import numpy as np
import pytest
from PIL import Image

from pienerf.viewer import build_app
from tests.pienerf.viewer.test_loop import free_port

CHROMIUM = shutil.which("chromium")
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


@pytest.mark.skipif(
    CHROMIUM is None and not os.environ.get("CI"),
    reason="chromium is not installed (apt-get install -y chromium); set CI=1 to require it",
)
def test_meshcat_page_drags_sets_pins_resets_and_shows_the_nerf(device, tmp_path):
    from playwright.sync_api import sync_playwright

    assert CHROMIUM is not None, "CI is set but chromium is missing: apt-get install -y chromium"
    app = build_app("plant", "meshcat", "127.0.0.1", free_port(), smoke=True, cache_dir=str(tmp_path))
    sim = app.simulation
    drag = sim.interaction.drag
    default_pins = len(sim.interaction.pins)
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=CHROMIUM,
                headless=True,
                args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"],
            )
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(app.viewer.url)
            loaded = lambda: page.evaluate("() => window.pienerf !== undefined && window.pienerf.stats.updates > 2")  # noqa: E731
            assert _poll(page, app, loaded, 60.0), "the page did not receive the body"
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

            # A click keeps a point picked; pin it; reset.
            pixel = page.evaluate(_FIND_BODY_PIXEL)  # where the swinging plant is now
            assert pixel is not None, "the plant left the middle of the view"
            page.mouse.click(*pixel)
            assert _poll(page, app, lambda: drag.dragging), f"the click did not pick: errors {app.errors}"
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
