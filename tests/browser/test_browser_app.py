"""Real-browser end-to-end tests of the app: Debian chromium driven by playwright.

Never downloads a browser (``executable_path=/usr/bin/chromium``); skipped only when that binary
is missing. WebGL is software-rendered here, so waits are generous and scenes small (a 640x480
simulated sequence). Screen positions of image pixels are computed in the page from the scene
node's world matrix and the three.js camera, then clicked; the app must report the same pixels.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from benchmarks.app import CHROMIUM, LAUNCH_ARGS  # one set of browser flags for tests and bench

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        not CHROMIUM.exists(), reason="Debian chromium (/usr/bin/chromium) is not installed"
    ),
]

viser = pytest.importorskip("viser")
playwright_api = pytest.importorskip("playwright.sync_api")

from app.gui import scene2d  # noqa: E402
from app.gui.project import Project  # noqa: E402
from app.gui.security import make_server  # noqa: E402
from app.gui.server import App  # noqa: E402
from registration.lens import HarrisModel  # noqa: E402
from tests.app.test_app import small_seq  # noqa: E402,F401  (session fixture: 4 frames 640x480)

VIEWPORT = {"width": 1280, "height": 800}
WIDE = {"width": 1440, "height": 900}
SHOTS = (
    Path(os.environ.get("AERIALREG_TEST_SHOTS", ""))
    if os.environ.get("AERIALREG_TEST_SHOTS")
    else None
)

# Screen (CSS px) of a pixel of the image node: node-local coordinates (x right, y down, image
# centre at the origin) -> world (the node's matrix) -> normalised device coordinates -> CSS px.
JS_SCREEN_OF = """([node, lx, ly]) => {
  const m = window.__viserMutable; const o = m.nodeRefFromName[node];
  if (!o) return null;
  o.updateMatrixWorld(true); m.camera.updateMatrixWorld();
  const V = o.position.constructor; const v = new V(lx, ly, 0);
  o.localToWorld(v); v.project(m.camera);
  const r = m.canvas.getBoundingClientRect();
  return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
}"""
# RGBA pixels of the rendered WebGL canvas at CSS points.
JS_PIXELS_AT = """(pts) => {
  const c = window.__viserMutable.canvas; const t = document.createElement('canvas');
  t.width = c.width; t.height = c.height; const g = t.getContext('2d'); g.drawImage(c, 0, 0);
  const r = c.getBoundingClientRect(); const s = c.width / r.width;
  return pts.map(([x, y]) => Array.from(g.getImageData(Math.floor((x - r.left) * s), Math.floor((y - r.top) * s), 1, 1).data));
}"""


def wait_until(cond, timeout=30.0, interval=0.1, what="condition"):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@pytest.fixture(scope="module")
def chromium():
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        yield b
        b.close()


class TestBrowser:
    """The shared Chromium as one test sees it: the pages it opens are closed when the test
    ends. A page left open keeps drawing its scene in software WebGL and reconnecting to its
    stopped server; the pages of earlier tests made the last test of this file take 93-112 s
    instead of 20 s."""

    __test__ = False  # not a test class

    def __init__(self, browser) -> None:
        self._browser = browser
        self.pages: list = []

    def new_page(self, **kwargs):
        page = self._browser.new_page(**kwargs)
        self.pages.append(page)
        return page


@pytest.fixture
def browser(chromium):
    b = TestBrowser(chromium)
    yield b
    for page in b.pages:
        if not page.is_closed():
            page.close()


@pytest.fixture
def live_app(tmp_path, small_seq):  # noqa: F811
    apps = []

    def start(**kw) -> App:
        server = make_server("127.0.0.1", 0, verbose=False)
        app = App(
            server,
            Project(tmp_path / "proj"),
            frames=str(small_seq / "frames"),
            base=str(small_seq / "base.png"),
            allowed_dirs=[tmp_path, small_seq],
            **kw,
        )
        app.start()
        app.worker.wait_idle()
        apps.append(app)
        return app

    yield start
    for app in apps:
        app.stop()


class Page:
    """A playwright page on the app, recording any request that leaves localhost."""

    def __init__(self, browser, port: int, viewport=VIEWPORT, connect_s: float = 30.0) -> None:
        self.port = port
        self.external: list[str] = []
        self.page = browser.new_page(viewport=viewport, accept_downloads=True)
        self.page.route("**/*", self._route)
        self.page.goto(f"http://127.0.0.1:{port}/")
        self.page.wait_for_function(
            "() => window.__viserMutable && window.__viserMutable.nodeRefFromName "
            "&& !document.body.innerText.includes('Connecting...')",
            timeout=connect_s * 1000,
        )
        self.close_notifications()

    def _route(self, route) -> None:
        url = route.request.url
        local = any(
            url.startswith(f"{scheme}://{host}:{self.port}")
            for scheme in ("http", "ws")
            for host in ("127.0.0.1", "localhost")
        )
        if local or url.startswith(("data:", "blob:")):
            route.continue_()
        else:
            self.external.append(url)
            route.abort()

    def close_notifications(self) -> None:
        # The "software WebGL" notice covers the canvas's top-left and swallows clicks.
        time.sleep(0.3)
        for btn in self.page.locator(".mantine-Notification-root button").all():
            try:
                btn.click(timeout=1000)
            except Exception:
                pass
        time.sleep(0.6)

    def wait_node(self, name: str, timeout=30.0) -> None:
        self.page.wait_for_function(
            f"() => window.__viserMutable.nodeRefFromName[{json.dumps(name)}] !== undefined",
            timeout=timeout * 1000,
        )

    def screen_of(self, node: str, geom, xy) -> tuple[float, float]:
        s = geom.scale
        lx = (xy[0] + 0.5 - geom.width / 2) * s
        ly = (xy[1] + 0.5 - geom.height / 2) * s
        return tuple(self.page.evaluate(JS_SCREEN_OF, [node, lx, ly]))

    def pixels(self, pts) -> np.ndarray:
        return np.array(self.page.evaluate(JS_PIXELS_AT, [list(map(float, p)) for p in pts]), float)

    def click_pixel(self, node: str, geom, xy) -> None:
        sx, sy = self.screen_of(node, geom, xy)
        # A notification left over the canvas swallows the click (and, hovered, never closes:
        # the app's "Suggested points" sat over a frame-1 target in every loaded run): a user
        # closes it first, and so does this.
        if not self.canvas_at(sx - 0.5, sy - 0.5):
            self.close_notifications()
            assert self.canvas_at(sx - 0.5, sy - 0.5), f"something covers the canvas at {sx, sy}"
        # viser casts its click ray through the pixel centre (clientX + 0.5).
        self.page.mouse.click(sx - 0.5, sy - 0.5)

    def canvas_at(self, x: float, y: float) -> bool:
        return self.page.evaluate(
            "([x, y]) => document.elementFromPoint(x, y)?.tagName === 'CANVAS'", [x, y]
        )

    def number_input(self, label: str):
        return self.page.locator(
            f"xpath=//p[normalize-space(.)={json.dumps(label, ensure_ascii=False)}]/ancestor::div[contains(@class,'mantine-Flex-root')][1]"
            "//input[not(@type='hidden')]"
        ).last

    def set_number(self, label: str, value) -> None:
        box = self.number_input(label)
        box.fill(str(value))
        box.press("Enter")

    def button(self, text: str):
        return self.page.get_by_role("button", name=text, exact=True).first

    def view_button(self, mode: str):
        """A "View" button: its label carries markers (▶ active, ✓ done) around the name."""
        import re

        return self.page.get_by_role("button", name=re.compile(rf"^(▶ )?{mode}( ✓)?$")).first

    def text(self) -> str:
        return self.page.inner_text("body")

    def count_dominant(self, channel: int, margin: int) -> int:
        """Pixels of a page screenshot whose RGB ``channel`` exceeds both others by ``margin``."""
        import cv2

        png = np.frombuffer(self.page.screenshot(), np.uint8)
        rgb = cv2.imdecode(png, cv2.IMREAD_COLOR)[..., ::-1].astype(int)
        others = np.delete(rgb, channel, axis=2).max(axis=2)
        return int(((rgb[..., channel] - others) > margin).sum())

    def shot(self, name: str) -> None:
        if SHOTS is not None:
            SHOTS.mkdir(parents=True, exist_ok=True)
            self.page.screenshot(path=str(SHOTS / f"{name}.png"))


JS_CANVAS_CENTRE = """() => { const r = window.__viserMutable.canvas.getBoundingClientRect();
  return [r.left + r.width / 2, r.top + r.height / 2]; }"""


def zoom_to(app: App, geom, xy, span_px: float = 200.0, page=None, node=None) -> None:
    """Point every client's camera at pixel ``xy`` of a plane, ``span_px`` image px across;
    with ``page`` and the plane's ``node``, wait until that browser shows ``xy`` at the centre."""
    from app.gui import scene2d

    centre = geom.world_from_pixel(np.asarray(xy, float))
    region = scene2d.PlaneGeometry(int(span_px), int(span_px * 0.75), position=tuple(centre))
    pose = scene2d.fit_camera([region])
    for client in app.server.get_clients().values():
        app.apply_camera(client, pose)
    if page is not None and node is not None:
        seen = []

        def there():
            seen[:] = [page.screen_of(node, geom, xy), page.page.evaluate(JS_CANVAS_CENTRE)]
            return np.hypot(*(np.subtract(seen[0], seen[1]))) < 2.0

        try:
            wait_until(there, what="the browser's camera at the zoomed pose")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: target on screen, canvas centre = {seen}") from None
    time.sleep(1.0)  # a software-WebGL render


def background_points(page, node, geom, gap=0.04):
    """Two screen points just outside the image (left, above or below it) inside the viewport,
    or None while the image fills the viewport."""
    w, h = geom.width, geom.height
    candidates = [
        [(-gap * w, 0.45 * h), (-gap * w, 0.55 * h)],
        [(0.45 * w, -gap * h), (0.55 * w, -gap * h)],
        [(0.45 * w, (1 + gap) * h), (0.55 * w, (1 + gap) * h)],
    ]
    for pair in candidates:
        pts = [page.screen_of(node, geom, p) for p in pair]
        if all(5 < x < VIEWPORT["width"] - 5 and 5 < y < VIEWPORT["height"] - 5 for x, y in pts):
            return pts
    return None


def grid_points(geom, n=5, margin=0.15):
    xs = np.linspace(geom.width * margin, geom.width * (1 - margin), n)
    ys = np.linspace(geom.height * margin, geom.height * (1 - margin), n)
    return np.array([(x, y) for y in ys for x in xs])


def rendered_matches_image(page: Page, node: str, geom, image_rgb: np.ndarray) -> float:
    """Correlation between canvas pixels and the expected image at a grid of image points."""
    import cv2

    pts = grid_points(geom, 7)
    screen = [page.screen_of(node, geom, p) for p in pts]
    got = page.pixels(screen)[:, :3].mean(axis=1)
    blurred = cv2.GaussianBlur(image_rgb, (0, 0), 1.5)
    want = np.array([blurred[int(round(y)), int(round(x))].mean() for x, y in pts])
    return float(np.corrcoef(got, want)[0, 1])


def test_loads_offline_gamma_changes_frame_and_straightness(browser, live_app, small_seq):  # noqa: F811
    import re

    import cv2

    app = live_app()
    cal = app.views["Calibrate"]
    cal.panel.grid_box.value = False  # reference lines off: compare pure image pixels
    # A line straight in the raw frame (clicked at γ = 0): its straightness depends on γ.
    for xy in ([40.0, 60.0], [320.0, 50.0], [600.0, 60.0]):
        cal.on_click("frame", np.array(xy), None)
    cal.finish_line()
    app.worker.wait_idle()
    page = Page(browser, app.server.get_port())
    page.wait_node("/calibrate/frame")
    geom = cal.scene.planes["frame"].geom
    raw = cv2.cvtColor(app.inputs.frame(0), cv2.COLOR_BGR2RGB)
    corr = wait_until(
        lambda: (c := rendered_matches_image(page, "/calibrate/frame", geom, raw)) > 0.8 and c,
        what="the frame on the canvas",
    )
    page.shot("calibrate")
    # Background just outside the image is the empty scene (uniform). The camera fits the image
    # to the viewport's shape, so take points beside it on whichever side has room on screen.
    pts = wait_until(
        lambda: background_points(page, "/calibrate/frame", geom),
        what="background visible beside the image",
    )
    bg = page.pixels(pts)
    assert np.ptp(bg[:, :3]) < 10, bg

    def overall() -> float:
        m = re.search(r"Overall: ([0-9.]+) px", page.text())
        return float(m.group(1)) if m else float("nan")

    at0 = wait_until(lambda: np.isfinite(overall()) and overall(), what="the straightness table")
    before = page.pixels(
        [page.screen_of("/calibrate/frame", geom, p) for p in grid_points(geom, 7)]
    )
    page.set_number("γ (exact)", 0.7)
    wait_until(lambda: app.state.gamma == pytest.approx(0.7), what="γ = 0.7 in the state")
    app.worker.wait_idle()
    corrected = cal.corrected_image(0, 0.7, None)
    wait_until(
        lambda: rendered_matches_image(page, "/calibrate/frame", geom, corrected) > 0.8,
        what="the corrected frame on the canvas",
    )
    # ... and it is the corrected image, not the raw one any more.
    assert rendered_matches_image(page, "/calibrate/frame", geom, raw) < 0.8
    after = page.pixels([page.screen_of("/calibrate/frame", geom, p) for p in grid_points(geom, 7)])
    assert np.abs(after - before)[:, :3].mean() > 5.0
    # The straightness table follows γ: the page shows the line's RMS at 0.7.
    expected = cal.scores()[1]
    wait_until(lambda: abs(overall() - expected) < 0.006, what=f"Overall {expected:.2f} px")
    assert abs(at0 - expected) > 0.05
    assert json.loads((app.project.session_path).read_text())["gamma"] == pytest.approx(0.7)
    page.shot("calibrate_gamma")
    assert page.external == [], page.external
    assert corr > 0.8


def screen_of_node(page: Page, node: str, lx: float, ly: float) -> tuple[float, float]:
    return tuple(page.page.evaluate(JS_SCREEN_OF, [node, lx, ly]))


@pytest.mark.slow
def test_seed_click_drag_and_disable_worst(browser, live_app, small_seq):  # noqa: F811
    import re

    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = live_app()
    app.views["Calibrate"].set_gamma(truth.gamma)
    page = Page(browser, app.server.get_port())
    page.view_button("Seed").click()
    wait_until(lambda: app.state.mode == "Seed", what="Seed view")
    app.worker.wait_idle()
    seed = app.views["Seed"]
    page.wait_node("/seed/frame")
    page.wait_node("/seed/base")
    time.sleep(1.0)
    fgeom, bgeom = seed.scene.planes["frame"].geom, seed.scene.planes["base"].geom
    w, h = app.inputs.frame_size
    raw_target = np.array([w * 0.45 + 0.3, h * 0.46 + 0.6])
    corrected_target = HarrisModel(truth.gamma, w, h).corrected_from_raw(raw_target[None])[0]
    base_target = truth.frame_to_base(0, raw_target[None])[0]
    # Zoomed in so that one CSS pixel is a fraction of an image pixel, as an analyst would.
    zoom_to(app, fgeom, corrected_target, page=page, node="/seed/frame")
    page.click_pixel("/seed/frame", fgeom, corrected_target)
    wait_until(lambda: app.state.seed_frame is not None, what="the frame click")
    zoom_to(app, bgeom, base_target, page=page, node="/seed/base")
    page.click_pixel("/seed/base", bgeom, base_target)
    wait_until(lambda: app.state.seed is not None, what="the map click")
    got = HarrisModel(truth.gamma, w, h).corrected_from_raw([app.state.seed_frame])[0]
    assert np.hypot(*(got - corrected_target)) < 1.0, (got, corrected_target)
    assert np.hypot(*(np.array(app.state.seed_base) - base_target)) < 1.0
    # The click fits the reference frame by itself; heading and scale appear in the panel.
    wait_until(lambda: app.state.current_reference() is not None, what="the fit to start")
    app.jobs.join(120)
    app.worker.wait_idle()
    first = app.state.current_reference()
    assert first.coarse and first.fine, app.errors
    page.page.wait_for_selector("text=heading", timeout=15000)
    # Drag the map marker (grabbed on its ring) by a known number of map pixels.
    page.wait_node("/seed/seed_base_1")
    app.worker.wait_idle()
    time.sleep(1.0)  # the marker's size for the current zoom has reached the browser
    shift = np.array([7.0, -5.0])
    a = np.array(page.screen_of("/seed/base", bgeom, base_target))
    b = np.array(page.screen_of("/seed/base", bgeom, base_target + shift))
    radius = seed.scene.markers[("base", 1)].radius  # world units; the ring is 0.6-1.0 of it
    grab = np.array(screen_of_node(page, "/seed/seed_base_1", 0.8 * radius, 0.0))
    page.page.mouse.move(*grab)
    page.page.mouse.down()
    for t in np.linspace(0.1, 1.0, 12):
        page.page.mouse.move(*(grab + t * (b - a)))
        time.sleep(0.05)
    page.page.mouse.up()
    wait_until(
        lambda: np.hypot(*(np.array(app.state.seed_base) - base_target - shift)) < 1.0,
        what="the seed moved by the drag",
    )
    # ... which moves the fit: a new one, for the new seed.
    wait_until(
        lambda: (r := app.state.current_reference()) is not None and r is not first,
        what="a new fit",
    )
    app.jobs.join(120)
    app.worker.wait_idle()
    moved = app.state.current_reference()
    assert moved.key["seed"][2:] == pytest.approx(list(base_target + shift), abs=1.0)
    assert moved.coarse and moved.fine
    page.shot("seed_dragged")
    # Disabling the worst control point lowers the RMS the page shows.
    app.fit_cameras(seed.scene.geoms())

    def rms() -> float:
        m = re.search(r"RMS of the enabled ([0-9.]+) px", page.text())
        return float(m.group(1)) if m else float("nan")

    r0 = wait_until(lambda: np.isfinite(rms()) and rms(), what="the control-point table")
    page.button("Disable worst").click()
    wait_until(lambda: rms() < r0, what="a lower RMS after disabling the worst point")
    assert "✗" in page.page.inner_text(".aerialreg-table")
    page.shot("seed_control_points")
    # A row click selects the point and centres the camera on it, frame point and map point:
    # the row whose points lie farthest from where the camera looks now.
    client = next(iter(app.server.get_clients().values()))
    table = seed.table
    look0 = np.asarray(client.camera.look_at)[:2]
    rows = page.page.locator(".aerialreg-table tr[data-row]:visible")
    ids = [int(rows.nth(i).get_attribute("data-row")) for i in range(min(rows.count(), 10))]

    def centre(rid):
        return np.asarray(seed.points._region(table, table.row(rid))[0].position[:2])

    far = max(range(len(ids)), key=lambda i: np.hypot(*(centre(ids[i]) - look0)))
    rid = ids[far]
    region = seed.points._region(table, table.row(rid))[0]
    tolerance = 0.05 * region.width * scene2d.WORLD_PER_PX
    assert np.hypot(*(centre(rid) - look0)) > 4 * tolerance  # the click has to move it
    rows.nth(far).click()
    wait_until(lambda: seed.points.cp.selected == rid, what="the row click to select the point")
    wait_until(
        lambda: np.hypot(*(np.asarray(client.camera.look_at)[:2] - centre(rid))) < tolerance,
        what="the camera centred on the row's points",
    )


@pytest.fixture(scope="module")
def turned_seq(small_seq, tmp_path_factory):  # noqa: F811
    """The small sequence over its map turned by 90° (``registration.synth.rebasing``)."""
    from registration.synth.rebasing import rebase

    return rebase(small_seq, tmp_path_factory.mktemp("turned") / "seq", 90.0, 1.0)


@pytest.mark.slow
def test_one_click_on_a_turned_map_shows_heading_and_second_pair_fixes_it(
    browser, turned_seq, tmp_path
):
    from app.gui import calls
    from registration.synth import load_truth
    from tests.app.test_app import angle_gap, heading_shown, true_heading

    truth = load_truth(turned_seq)
    server = make_server("127.0.0.1", 0, verbose=False)
    app = App(
        server,
        Project(tmp_path / "proj"),
        frames=str(turned_seq / "frames"),
        base=str(turned_seq / "base.png"),
        allowed_dirs=[tmp_path, turned_seq],
    )
    try:
        app.start()
        app.views["Calibrate"].set_gamma(truth.gamma)
        app.worker.wait_idle()
        page = Page(browser, app.server.get_port())
        page.view_button("Seed").click()
        wait_until(lambda: app.state.mode == "Seed", what="Seed view")
        app.worker.wait_idle()
        seed = app.views["Seed"]
        page.wait_node("/seed/frame")
        page.wait_node("/seed/base")
        fgeom, bgeom = seed.scene.planes["frame"].geom, seed.scene.planes["base"].geom
        harris = HarrisModel(truth.gamma, *app.inputs.frame_size)

        def click_pair(raw):
            corrected = harris.corrected_from_raw(np.array([raw]))[0]
            base = truth.frame_to_base(0, np.array([raw]))[0]
            zoom_to(app, fgeom, corrected, page=page, node="/seed/frame")
            page.click_pixel("/seed/frame", fgeom, corrected)
            zoom_to(app, bgeom, base, page=page, node="/seed/base")
            page.click_pixel("/seed/base", bgeom, base)

        def shown(where: str, source: str) -> float | None:
            text = page.text()
            line = next((ln for ln in text.splitlines() if ln.startswith(where)), "")
            return heading_shown(line, where) if source in line else None

        # One click pair: the heading the library estimated appears, close to the truth (~90°).
        raw1 = (300.0, 220.0)
        click_pair(raw1)
        wait_until(lambda: app.state.seed is not None, what="pair 1")
        one = wait_until(
            lambda: shown("Coarse step", "estimated from the click"),
            timeout=120,
            what="the heading estimated from one click",
        )
        want, _ = true_heading(truth, 0, raw1)
        assert 80.0 < want < 100.0
        assert angle_gap(one, want) < 5.0, (one, want)
        assert app.state.current_reference().coarse, app.errors
        page.shot("seed_turned_one_click")
        # A second pair fixes heading and scale exactly: the panel shows the pairs' heading,
        # and the coarse step's (which the library took from the two pairs).
        app.jobs.join(120)
        app.worker.wait_idle()
        # Under load a click during the panel's redraw after the fit can be lost (seen once in
        # two full-suite runs): pressed again when it did not take.
        for attempt in range(3):
            page.button("Pair 2").click()
            try:
                wait_until(lambda: app.state.seed_pair == 2, timeout=10, what="pair 2 active")
                break
            except AssertionError:
                if attempt == 2:
                    raise
        click_pair((460.0, 330.0))
        wait_until(lambda: app.state.seed2 is not None, what="pair 2")
        exact = calls.heading_from_pairs(
            app.state.seed, app.state.seed2, truth.gamma, app.inputs.frame_size
        ).heading_deg
        two = wait_until(
            lambda: shown("Coarse step", "fixed by the two pairs"),
            timeout=120,
            what="the heading fixed by two pairs",
        )
        assert two == pytest.approx(exact, abs=0.051)
        assert shown("Pairs", "fixed by the two pairs") == pytest.approx(exact, abs=0.051)
        assert app.state.current_reference().coarse.heading_deg == pytest.approx(exact, abs=1e-6)
        assert angle_gap(exact, want) < 2.0
        page.shot("seed_turned_two_pairs")
        app.jobs.join(120)
    finally:
        app.stop()


@pytest.fixture
def registered_app(live_app, small_seq):  # noqa: F811
    """A live app with the reference fitted and the 4 frames registered (in process)."""
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = live_app()
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Seed")
    seed = app.views["Seed"]
    fxy = np.array([[320.0, 240.0]])
    bxy = truth.frame_to_base(0, fxy)[0]
    seed.place_seed("frame", tuple(fxy[0]))
    seed.place_seed("base", tuple(bxy))
    app.jobs.join(120)
    app.worker.wait_idle()
    app.set_mode("Sequence")
    assert app.views["Sequence"].run()
    app.jobs.join(300)
    app.worker.wait_idle()
    assert app.state.result is not None and app.state.result.is_ok(3), app.errors
    return app, truth, bxy


@pytest.mark.slow
def test_scrub_plot_click_and_table2(browser, registered_app):
    app, truth, bxy = registered_app
    seq = app.views["Sequence"]
    page = Page(browser, app.server.get_port())
    page.wait_node("/sequence/base")
    geom = seq.scene.planes["base"].geom
    pts = [page.screen_of("/sequence/base", geom, p) for p in grid_points(geom, 9, 0.3)]
    time.sleep(1.5)
    before = page.pixels(pts)
    page.set_number("Frame", 3)
    wait_until(lambda: app.shown["Sequence"][0] == 3, what="the scrubber to show frame 3")
    wait_until(
        lambda: np.abs(page.pixels(pts) - before)[:, :3].mean() > 2.0, what="a changed image"
    )
    assert app.shown["Sequence"][0] == 3
    # The app redraws the chart when the frame changes (the current frame's marker): let that
    # reach the page first, or the legend goes blank mid-hover.
    app.worker.wait_idle()
    time.sleep(1.0)
    # Clicking a point of the per-frame chart shows that frame: hover along the chart until its
    # legend names frame 1, then click.
    chart = page.page.locator(".uplot", has_text="Per-frame").first
    chart.scroll_into_view_if_needed()
    over = chart.locator(".u-over")
    box = over.bounding_box()
    legend = chart.locator(".u-legend .u-series").first.locator(".u-value")
    mid_y = box["y"] + box["height"] / 2

    def legend_at(fx: float) -> str:
        # A move that always changes the position (a move to where the pointer already is
        # sends no mousemove, and the page's click handler reads the last hovered frame), then
        # wait until the legend reads the same three times (a loaded machine renders late).
        x = box["x"] + fx * box["width"]
        page.page.mouse.move(x, mid_y + 3)
        page.page.mouse.move(x, mid_y)
        reads, t0 = [], time.monotonic()
        while time.monotonic() - t0 < 5:
            time.sleep(0.15)
            reads.append(legend.inner_text().strip())
            if len(reads) >= 3 and len(set(reads[-3:])) == 1:
                break
        return reads[-1]

    fx = next((f for f in np.linspace(0.02, 0.98, 25) if legend_at(f) == "1"), None)
    assert fx is not None, "no pointer position over the chart shows frame 1"
    assert legend_at(fx) == "1"  # still there after the pointer comes back
    # A locator click (Playwright checks the chart is what receives it): a raw mouse.click at
    # the same viewport point was, one run in four, never delivered to the page (no
    # pointerdown reached the document), while this click in the same state was.
    over.click(position={"x": fx * box["width"], "y": box["height"] / 2})
    wait_until(lambda: app.shown["Sequence"][0] == 1, what="the chart click to show frame 1")
    page.shot("sequence")
    # Evaluate: a suggested point confirmed, a mark and a proposal; the unconfirmed proposal is
    # not in Table 2.
    page.view_button("Evaluate").click()
    wait_until(lambda: app.state.mode == "Evaluate", what="Evaluate view")
    app.worker.wait_idle()
    ev = app.views["Evaluate"]
    page.wait_node("/evaluate/frame")
    fgeom = ev.scene.planes["frame"].geom
    page.button("Suggest").click()
    wait_until(lambda: ("NW", 0) in app.state.pending, what="suggested points")
    page.page.wait_for_selector("text=suggested: a corner", timeout=15000)
    page.button("Confirm").click()
    wait_until(lambda: ("NW", 0) not in app.state.pending, what="the suggestion confirmed")
    ground = truth.frame_to_base(0, np.array([app.state.points["NW"][0]]))
    ev.set_frame(1)
    app.worker.wait_idle()
    time.sleep(0.5)
    page.click_pixel("/evaluate/frame", fgeom, truth.base_to_frame(1, ground)[0])
    wait_until(lambda: 1 in app.state.points.get("NW", {}), what="the mark in frame 1")
    page.button("Propose next").click()
    wait_until(lambda: ("NW", 2) in app.state.pending, what="a proposal in frame 2")
    page.page.wait_for_selector("text=proposed, NCC", timeout=15000)
    page.button("Compute Table 2").click()
    wait_until(lambda: app.state.report is not None, what="Table 2")
    page.page.wait_for_selector("text=pending proposals left out", timeout=15000)
    assert app.state.report.table.frames["NW"] == [1]
    page.page.wait_for_selector("text=Post-Local", timeout=15000)
    page.shot("evaluate_table2")
    # Table 2 downloads as CSV (and markdown) from its panel.
    with page.page.expect_download(timeout=15000) as dl:
        page.button("CSV").click()
    path = dl.value.path()
    assert Path(path).read_text() == app.state.report.table.to_csv()
    with page.page.expect_download(timeout=15000) as dl:
        page.button("Markdown").click()
    assert "Post-Local" in Path(dl.value.path()).read_text()
    # Export (video + transforms by default) from the Sequence view, then download the video.
    page.view_button("Sequence").click()
    wait_until(lambda: app.state.mode == "Sequence", what="Sequence view")
    page.page.get_by_text("Export", exact=True).first.click()
    # Under a loaded full-suite run a press can be lost (seen once in four runs): pressed
    # again when no export started.
    for attempt in range(3):
        page.button("Export the ticked formats").click()
        try:
            wait_until(
                lambda: app.views["Sequence"].exporter.summary is not None or app.jobs.busy,
                timeout=20,
                what="the export to start",
            )
            break
        except AssertionError:
            if attempt == 2:
                raise
    try:
        page.page.wait_for_selector("text=Export done", timeout=120000)
    except Exception as exc:  # say what the app said, not only that the text never came
        raise AssertionError(f"no 'Export done': {app.notices[-5:]}, {app.errors[-3:]}") from exc
    out = app.project.folder / "exports"
    with page.page.expect_download(timeout=30000) as dl:
        page.button("Download").click()
    # The video and its world file (the plain base's own pixel grid): one zip.
    assert dl.value.suggested_filename == "exports_mp4.zip"
    import zipfile

    with zipfile.ZipFile(dl.value.path()) as z:
        assert sorted(z.namelist()) == ["registered.mp4", "registered.wld"]
        assert z.read("registered.mp4") == (out / "registered.mp4").read_bytes()
    # Again: the files exist, so the app asks; a new numbered folder is one answer.
    page.button("Export the ticked formats").click()
    page.page.wait_for_selector("text=Files exist", timeout=15000)
    page.button("Write into exports-2").click()
    wait_until(
        lambda: (app.project.folder / "exports-2" / "transforms.json").exists(),
        timeout=120,
        what="the export into exports-2",
    )
    page.shot("sequence_export")


JS_OVERFLOW = """() => {
  // Elements of the control panel and of floating panels whose box runs past their panel's
  // right edge (text or tables that would be cut off), ignoring our own scroll containers.
  const out = [];
  const panels = Array.from(document.querySelectorAll('.mantine-Paper-root, [class*="panel" i]'))
    .filter((p) => p.getBoundingClientRect().width > 200);
  for (const panel of panels) {
    const pr = panel.getBoundingClientRect();
    panel.querySelectorAll('*').forEach((e) => {
      if (e.closest('.aerialreg-scroll') || e.closest('.u-wrap')) return;
      // Resize grips sit on the edge by design: only content with text counts.
      if (!(e.textContent || '').trim()) return;
      const r = e.getBoundingClientRect();
      if (r.width > 0 && r.right > pr.right + 2 && r.left < pr.right) {
        out.push((e.tagName + '.' + (typeof e.className === 'string' ? e.className : '') + ' ' +
          Math.round(r.left) + '-' + Math.round(r.right) + ' in ' + Math.round(pr.left) + '-' +
          Math.round(pr.right) + ' ' + (e.textContent || '').slice(0, 30)).trim());
      }
    });
  }
  return Array.from(new Set(out)).slice(0, 20);
}"""


@pytest.mark.slow
def test_each_view_at_1440x900_is_drawn_and_nothing_overflows(browser, registered_app):
    import cv2

    app, truth, bxy = registered_app
    ev = app.views["Evaluate"]
    app.set_mode("Evaluate")
    for k in (0, 1):
        ev.set_frame(k)
        ev.on_click("frame", truth.base_to_frame(k, bxy[None])[0], None)
    assert ev.compute_table()
    app.jobs.join(60)
    page = Page(browser, app.server.get_port(), viewport=WIDE)
    for mode in ("Calibrate", "Seed", "Sequence", "Evaluate", "Traffic"):
        page.view_button(mode).click()
        wait_until(lambda m=mode: app.state.mode == m, what=f"{mode} view")
        app.worker.wait_idle()
        page.wait_node(f"/{mode.lower()}")
        time.sleep(2.5)  # camera fit and textures (software WebGL)
        png = np.frombuffer(page.page.screenshot(), np.uint8)
        shot = cv2.imdecode(png, cv2.IMREAD_COLOR)
        page.shot(f"wide_{mode.lower()}")
        rect = page.page.evaluate(
            "() => { const r = window.__viserMutable.canvas.getBoundingClientRect();"
            " return [r.left, r.top, r.width, r.height]; }"
        )
        x, y, w, h = (int(v) for v in rect)
        canvas = shot[y : y + h, x : x + w].astype(float)
        # Drawn: the canvas is mostly the images, not a blank background.
        assert canvas.std() > 20, f"{mode}: blank canvas (std {canvas.std():.1f})"
        busy = (np.abs(np.diff(canvas.mean(axis=2), axis=1)) > 8).mean()
        assert busy > 0.05, f"{mode}: canvas shows no image ({busy:.3f} edge pixels)"
        overflow = page.page.evaluate(JS_OVERFLOW)
        assert overflow == [], f"{mode}: panel content overflows: {overflow}"
    # The check itself sees an overflow: a wide line of text put into the panel.
    page.page.evaluate(
        "() => { const d = document.createElement('div'); d.id = 'wide-probe';"
        " d.style.width = '3000px'; d.textContent = 'x'.repeat(50);"
        " document.querySelector('.mantine-Paper-root').appendChild(d); }"
    )
    assert page.page.evaluate(JS_OVERFLOW) != []


def test_the_gamma_slider_previews_while_it_is_dragged(browser, live_app):
    """The γ slider dragged with the mouse held down: the frame is corrected for the slider's
    γ while the button is still down (the preview follows the drag), not only on release."""
    app = live_app()
    page = Page(browser, app.server.get_port())
    page.wait_node("/calibrate/frame")
    slider = page.page.locator(
        "xpath=//p[normalize-space(.)='γ']/ancestor::div[contains(@class,'mantine-Flex-root')][1]"
        "//*[@role='slider']"
    ).first
    thumb = slider.bounding_box()
    track = slider.locator("xpath=ancestor::div[contains(@class,'mantine-Slider-root')][1]")
    right = track.bounding_box()
    x, y = thumb["x"] + thumb["width"] / 2, thumb["y"] + thumb["height"] / 2
    page.page.mouse.move(x, y)
    page.page.mouse.down()
    seen = []
    try:
        for i in range(1, 11):
            page.page.mouse.move(x + i * (right["x"] + right["width"] - x) * 0.05, y)
            time.sleep(0.15)
            with app.state.lock:
                seen.append(app.state.gamma)

        def previewed():
            with app.state.lock:
                g = app.state.gamma
            shown = app.shown.get("Calibrate")
            return g > 0.05 and shown is not None and shown[1] == pytest.approx(g) and g

        during = wait_until(previewed, what="the preview of the dragged γ, the button still down")
    finally:
        page.page.mouse.up()
    assert len(set(seen)) >= 3, seen  # γ followed the drag step by step
    assert during > 0.05


def test_the_pointer_readout_gives_the_pixel_and_map_coordinates_under_the_mouse(browser, live_app):
    """The mouse over the map in the Seed view: the line at the canvas's bottom left gives the
    map pixel under it (within the screen pixel's size); over a georeferenced map also its map
    coordinates through the map's affine (pixel (x, y) at A (x + 0.5, y + 0.5))."""
    import re

    app = live_app()
    app.set_mode("Seed")
    app.worker.wait_idle()
    page = Page(browser, app.server.get_port())
    page.wait_node("/seed/base")
    geom = app.views["Seed"].scene.planes["base"].geom
    target = (300.0, 200.0)
    sx, sy = page.screen_of("/seed/base", geom, target)
    page.page.mouse.move(sx + 3, sy + 3)
    page.page.mouse.move(sx, sy)
    text = wait_until(
        lambda: page.page.locator("#aerialreg-pointer").text_content() or "", what="the readout"
    )
    x, y = (float(v) for v in re.match(r"map px ([-0-9.]+), ([-0-9.]+)$", text).groups())
    # One screen pixel spans this many map pixels at the view's zoom.
    sx2, _ = page.screen_of("/seed/base", geom, (target[0] + 100, target[1]))
    per_screen_px = 100 / (sx2 - sx)
    assert abs(x - target[0]) <= per_screen_px + 0.1 and abs(y - target[1]) <= per_screen_px + 0.1
    # A georeferenced map (the published description of the planes, as the app sends it for
    # a GeoTIFF base): the map coordinates of that pixel.
    page.page.evaluate(
        """() => { const p = window.aerialregPlanes.planes.find((q) => q.node === '/seed/base');
          Object.assign(p, {affine: [0.5, 0, 500000, 0, -0.5, 4000000], unit: 'metre',
          crs: 'EPSG:32643'}); }"""
    )
    text = page.page.evaluate("([x, y]) => window.aerialregPointerAt(x, y)", [sx, sy])
    m = re.match(
        r"map px ([-0-9.]+), ([-0-9.]+) · ([0-9.]+), ([0-9.]+) metre \(EPSG:32643\)$", text
    )
    assert m, text
    px, py, east, north = (float(v) for v in m.groups())
    assert east == pytest.approx(500000 + 0.5 * (px + 0.5), abs=0.06)
    assert north == pytest.approx(4000000 - 0.5 * (py + 0.5), abs=0.06)
    # Off every image: nothing.
    assert page.page.evaluate("([x, y]) => window.aerialregPointerAt(x, y)", [2, 2]) == ""


def test_two_tabs_moving_sliders_stay_consistent(browser, live_app):
    app = live_app()
    a = Page(browser, app.server.get_port())
    b = Page(browser, app.server.get_port())
    values_a = [0.1, 0.3, 0.5, 0.2]
    values_b = [0.15, 0.35, 0.45, 0.25]
    # Each tab types and leaves the box (a focused viser number box does not take values that
    # arrive from the server meanwhile, and may send its own again on blur: a frontend race
    # that made this test flaky; leaving the box is what a user does before looking at the
    # other tab).
    for va, vb in zip(values_a, values_b, strict=True):
        for p, v in ((a, va), (b, vb)):
            p.set_number("γ (exact)", v)
            p.number_input("γ (exact)").evaluate("e => e.blur()")
    time.sleep(1.0)
    app.worker.wait_idle()
    time.sleep(0.8)  # the settle (full-resolution) render
    app.worker.wait_idle()
    g = app.state.gamma
    assert g in values_a + values_b
    cal = app.views["Calibrate"]
    assert cal.panel.gamma_number.value == pytest.approx(g)
    assert app.shown["Calibrate"][1] == pytest.approx(g)  # the image shown is for the final γ
    assert json.loads(app.project.session_path.read_text())["gamma"] == pytest.approx(g)
    # Both boxes show the state's γ.
    seen = []

    def agreed():
        boxes = [float(p.number_input("γ (exact)").input_value()) for p in (a, b)]
        with app.state.lock:
            state = app.state.gamma
        seen[:] = [boxes, state, cal.panel.gamma_number.value]
        return all(v == pytest.approx(state) for v in boxes) and state

    try:
        g = wait_until(agreed, what="both pages' γ boxes to show the state's γ")
    except AssertionError as exc:
        raise AssertionError(f"{exc}: boxes, state, server widget = {seen}") from None
    assert g in values_a + values_b
    app.worker.wait_idle()
    time.sleep(0.8)  # the settle render
    app.worker.wait_idle()
    assert cal.panel.gamma_number.value == pytest.approx(g)
    assert app.shown["Calibrate"][1] == pytest.approx(g)


def test_escaping_glob_and_oversized_upload_refused(browser, live_app, tmp_path, small_seq):  # noqa: F811
    # tmp_path is allowed; tmp_path/../secret is not. The glob's fixed part lies inside.
    secret = tmp_path.parent / f"{tmp_path.name}-secret"
    secret.mkdir()
    (secret / "s.png").write_bytes((small_seq / "base.png").read_bytes())
    (tmp_path / "d").mkdir()
    app = live_app(max_upload_mb=0.01)
    page = Page(browser, app.server.get_port())
    page.page.get_by_text("Inputs", exact=True).first.click()
    time.sleep(0.5)
    frames_box = page.number_input("Frames (video, folder, glob)")
    frames_box.fill(f"{tmp_path}/*/../../{secret.name}/*.png")
    frames_box.press("Enter")
    page.button("Open paths").click()
    page.page.wait_for_selector("text=Path refused", timeout=15000)
    assert "outside the allowed folders" in page.page.inner_text("body")
    assert app.inputs.frames_path == str(small_seq / "frames")
    big = tmp_path / "big.mp4"
    big.write_bytes(b"\0" * 50_000)
    page.page.locator("input[type=file]").first.set_input_files(str(big))
    page.page.wait_for_selector("text=Upload refused", timeout=15000)
    page.shot("refused")
    # Still serving: the γ box still drives the app.
    page.close_notifications()
    page.set_number("γ (exact)", 0.3)
    wait_until(lambda: app.state.gamma == pytest.approx(0.3), what="the app still responding")


JS_OPEN_WS = """([url, proto]) => new Promise((resolve) => {
  const ws = new WebSocket(url, [proto]);
  ws.onopen = () => { ws.close(); resolve('open'); };
  ws.onerror = () => resolve('error');
  setTimeout(() => resolve('timeout'), 10000);
})"""


def test_page_from_another_local_origin_cannot_connect(browser, live_app, tmp_path):
    import functools
    import threading
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    app = live_app()
    port = app.server.get_port()
    url, proto = f"ws://127.0.0.1:{port}", f"viser-v{viser.__version__}"
    (tmp_path / "index.html").write_text("<html><body>another local app</body></html>")
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(tmp_path))
    other = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    try:
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{other.server_address[1]}/")
        assert page.evaluate(JS_OPEN_WS, [url, proto]) == "error"
        page.close()
    finally:
        other.shutdown()
    assert any("differs from the served address" in r for r in app.server.origin_policy.refused)
    # The app's own page connects (its Origin is the served address).
    own = Page(browser, port)
    assert own.page.evaluate(JS_OPEN_WS, [url, proto]) == "open"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(project: Path, seq: Path, port: int) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "app.cli",
        "app",
        "--frames",
        str(seq / "frames"),
        "--base",
        str(seq / "base.png"),
        "--project",
        str(project),
        "--port",
        str(port),
    ]
    # Its log goes to a file: a pipe nobody reads fills up with progress lines and blocks the
    # server mid-run.
    log_path = project.parent / f"{project.name}-server-{time.monotonic_ns()}.log"
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log_file, text=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return proc
        except OSError:
            if proc.poll() is not None:
                raise AssertionError(f"server exited: {log_path.read_text()[-2000:]}") from None
            time.sleep(0.2)
    proc.kill()
    raise AssertionError("server did not start")


@pytest.mark.slow
def test_kill_mid_sequence_and_restart_keeps_frames(browser, tmp_path_factory):
    from registration.synth import SimConfig, load_truth, simulate

    seq = tmp_path_factory.mktemp("longseq")
    simulate(seq, SimConfig(frame_size=(640, 480), n_frames=6, video=False, seed=3))
    truth = load_truth(seq)
    project = tmp_path_factory.mktemp("proj")
    fxy = np.array([320.0, 240.0])
    bxy = truth.frame_to_base(0, fxy[None])[0]
    # A session with γ and the seed already decided (as the analyst would have left it).
    Project(project).save(
        {
            "gamma": truth.gamma,
            "gamma_set": True,
            "seed_frame": list(fxy),
            "seed_base": list(bxy),
            "mode": "Sequence",
        }
    )
    port = _free_port()
    proc = _serve(project, seq, port)
    records = project / "result" / "frames"
    try:
        page = Page(browser, port, connect_s=90.0)
        page.button("Register all frames").click()
        wait_until(
            lambda: records.is_dir() and len(list(records.glob("*.json"))) >= 2,
            timeout=120,
            interval=0.02,
            what="two registered frames",
        )
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        page.page.close()
    finally:
        if proc.poll() is None:
            proc.kill()

    def own_registration(path):  # the sequence adjustment adds to a record, never redoes it
        rec = json.loads(path.read_text())
        return rec["model"], rec["stats"].get("time_s")

    done = {p.name: own_registration(p) for p in records.glob("*.json")}
    assert 2 <= len(done) < 6, f"killed too late to test resuming: {len(done)} frames done"
    proc = _serve(project, seq, port)
    try:
        page = Page(browser, port, connect_s=90.0)
        page.page.wait_for_selector(f"text={len(done)} ok", timeout=30000)
        page.button("Register all frames").click()
        wait_until(
            lambda: len(list(records.glob("*.json"))) == 6,
            timeout=180,
            what="all frames registered",
        )
        page.page.wait_for_selector("text=6 ok", timeout=60000)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
    after = {p.name: own_registration(p) for p in records.glob("*.json")}
    assert all(after[name] == own for name, own in done.items()), "finished frames were redone"
