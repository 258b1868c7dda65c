"""End to end in a real browser: open the viewer, click the body, drag it with the mouse, see it move.

Needs Debian's ``chromium`` (``apt-get install -y chromium``) and the ``playwright`` package. Skipped when
chromium is absent, unless the environment variable CI is set: then it must run.
"""

from __future__ import annotations

import threading

import pytest
import torch

from pienerf.viewer import build_app
from tests.apps import chromium
from tests.apps.chromium import requires_chromium
from tests.pienerf.viewer.test_loop import free_port

pytestmark = pytest.mark.browser


def _poll(page, condition, seconds: float = 15.0) -> bool:
    """Let the page and the server work until ``condition`` holds or ``seconds`` pass."""
    for _ in range(int(seconds / 0.1)):
        if condition():
            return True
        page.wait_for_timeout(100)
    return condition()


@requires_chromium
def test_click_and_drag_moves_the_body(device, tmp_path):
    from playwright.sync_api import sync_playwright

    app = build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True)
    sim = app.simulation
    drag = sim.interaction.drag
    loop = threading.Thread(target=app.run, kwargs={"frame_seconds": 0.02}, daemon=True)
    loop.start()
    try:
        with sync_playwright() as playwright:
            browser = chromium.launch(playwright)
            page = browser.new_page(viewport={"width": 800, "height": 600})
            page.goto(f"http://127.0.0.1:{app.viewer.port}")
            page.wait_for_selector("canvas", timeout=60_000)
            assert _poll(page, lambda: len(app.viewer.server.get_clients()) > 0, 60.0)
            page.wait_for_timeout(1500)  # the client receives the scene and the camera

            # Click: find a pixel on the plant's mesh above the pot (the server picks with the click's ray).
            picked = None
            for dy in (-40, -80, -120, -160, 0, 40):
                for dx in (0, 30, -30, 60, -60):
                    x, y = 400 + dx, 300 + dy
                    page.mouse.click(x, y)
                    if _poll(page, lambda: drag.dragging, 1.0):
                        on_mesh = drag.hit.particle == -1 and float(drag.hit.rest[1]) > 0.4  # above the pinned pot
                        app.submit("release", sim.release)
                        assert _poll(page, lambda: not drag.dragging)
                        if on_mesh:
                            picked = (x, y)
                            break
                if picked:
                    break
            assert picked is not None, "no click in the middle of the view hit the plant's mesh"

            # Drag: press on the body, move right, and watch the picked point follow.
            x, y = picked
            page.mouse.move(x, y)
            page.mouse.down()
            page.mouse.move(x + 20, y, steps=4)
            assert _poll(page, lambda: drag.dragging), "the drag on the mesh did not reach the server"
            start = drag.hit.world.clone()
            page.mouse.move(x + 160, y, steps=16)
            moved = lambda: float(drag.position(sim.state.q)[0] - start[0]) > 0.02  # noqa: E731
            assert _poll(page, lambda: drag.dragging and moved()), (
                f"picked {drag.hit}, target {drag.target}, t = {sim.time:.2f} s, errors {app.errors}")
            target_shift = drag.target - start
            page.screenshot(path=str(tmp_path / "drag.png"))
            page.mouse.up()
            assert _poll(page, lambda: not drag.dragging)
            browser.close()
        assert float(target_shift[0]) > 0.05 and abs(float(target_shift[1])) < float(target_shift[0])
        assert (tmp_path / "drag.png").stat().st_size > 1000
        assert not torch.isnan(sim.state.q).any()
    finally:
        app.stop.set()
        loop.join(30)
        app.viewer.close()


@requires_chromium
def test_viser_status_and_message_show_without_scrolling(device):
    from playwright.sync_api import sync_playwright

    app = build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True)
    loop = threading.Thread(target=app.run, kwargs={"frame_seconds": 0.05}, daemon=True)
    loop.start()
    try:
        with sync_playwright() as playwright:
            browser = chromium.launch(playwright)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(f"http://127.0.0.1:{app.viewer.port}")
            app.viewer.report("a message to find")
            for text in ("fps", "a message to find", "ms,"):
                line = page.get_by_text(text).first
                line.wait_for(timeout=60_000)
                box = line.bounding_box()
                assert box is not None and 0 <= box["y"] and box["y"] + box["height"] <= 800, (text, box)
            browser.close()
    finally:
        app.stop.set()
        loop.join(30)
        app.close()
