"""In-process tests of the browser app: a real ViserServer on a free port, no browser.

Handlers are driven by setting widget values (which runs their callbacks synchronously, as a
browser update would) and by feeding click rays to ``App.handle_click``; the state, the saved
project and what was handed to viser are checked.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

viser = pytest.importorskip("viser")

from app.gui import scene2d  # noqa: E402
from app.gui.project import Project, write_atomic  # noqa: E402
from app.gui.security import make_server  # noqa: E402
from app.gui.server import App  # noqa: E402
from app.gui.state import AppState  # noqa: E402
from app.gui.worker import LatestWorker  # noqa: E402
from registration.lens import HarrisModel  # noqa: E402
from registration.render import viz  # noqa: E402

CAMERA = (0.05, 0.02, -1.0)  # an off-centre camera so click rays are oblique


@pytest.fixture(scope="session")
def small_seq(tmp_path_factory) -> Path:
    """A 4-frame 640x480 simulated sequence (γ = 0.7) with its base map."""
    from registration.synth import SimConfig, simulate

    out = tmp_path_factory.mktemp("seq")
    simulate(out, SimConfig(frame_size=(640, 480), n_frames=4, video=False, seed=1))
    return out


def start_app(project_dir: Path, seq: Path | None, **kw) -> App:
    server = make_server("127.0.0.1", 0, verbose=False)
    app = App(
        server,
        Project(project_dir),
        frames=str(seq / "frames") if seq else None,
        base=str(seq / "base.png") if seq else None,
        allowed_dirs=[project_dir, seq] if seq else [project_dir],
        **kw,
    )
    app.start()
    app.worker.wait_idle()
    return app


@pytest.fixture
def make_app():
    apps: list[App] = []

    def make(project_dir, seq, **kw) -> App:
        app = start_app(project_dir, seq, **kw)
        apps.append(app)
        return app

    yield make
    for app in apps:
        app.stop()


def click(app: App, plane: scene2d.ImagePlane, xy) -> tuple[str, np.ndarray] | None:
    o, d = plane.geom.ray_towards_pixel(xy, CAMERA)
    return app.handle_click(o, d)


# ---------------------------------------------------------------- pure helpers


def test_pixel_world_round_trip_and_oblique_ray_pick():
    g = scene2d.PlaneGeometry(2560, 1920, position=(0.7, -0.2, 0.0))
    xy = np.array([[0.0, 0.0], [2559.0, 1919.0], [1234.567, 89.25]])
    assert np.allclose(g.pixel_from_world(g.world_from_pixel(xy)), xy, atol=1e-9)
    # Pixel (0, 0)'s centre is half a pixel inside the plane's top-left corner.
    corner = np.array(g.position[:2]) - np.array(g.render_size) / 2
    assert np.allclose(g.world_from_pixel([0.0, 0.0])[:2], corner + 0.5 * g.scale)
    for target in xy:
        o, d = g.ray_towards_pixel(target, (3.0, -2.0, -1.5))
        assert np.allclose(g.pixel_from_ray(o, d), target, atol=1e-6)
    assert g.contains([-0.5, -0.5]) and not g.contains([2559.5, 0.0])
    assert g.pixel_from_ray((0, 0, -1), (1, 0, 0)) is None  # parallel ray
    assert g.pixel_from_ray((0, 0, -1), (0, 0, -1)) is None  # pointing away


def test_segments_world_is_float32_and_on_plane():
    g = scene2d.PlaneGeometry(100, 50)
    seg = scene2d.segments_world(g, [[0, 0]], [[99, 49]])
    assert seg.dtype == np.float32 and seg.shape == (1, 2, 3)
    assert np.allclose(g.pixel_from_world(seg[0].astype(float)), [[0, 0], [99, 49]], atol=1e-3)


def test_fit_camera_sees_both_planes():
    a = scene2d.PlaneGeometry(320, 240, position=(0.16, 0.12, 0))
    b = scene2d.PlaneGeometry(768, 608, position=(0.4 + 0.384, 0.304, 0))
    pose = scene2d.fit_camera([a, b])
    pos, look = np.array(pose["position"]), np.array(pose["look_at"])
    assert pos[2] < 0 and np.allclose(pos[:2], look[:2])
    half = -pos[2] * np.tan(pose["fov"] / 2)
    for g in (a, b):
        w, h = g.render_size
        assert abs(g.position[0] - look[0]) + w / 2 <= half * 1.34 + 1e-9  # 4:3 viewport
        assert abs(g.position[1] - look[1]) + h / 2 <= half + 1e-9


def test_latest_worker_drops_stale_requests_and_survives_errors():
    errors = []
    w = LatestWorker(on_error=lambda key, exc: errors.append(key))
    gate = threading.Event()
    ran = []
    w.submit("a", lambda: (gate.wait(5), ran.append("first")))
    time.sleep(0.05)  # "first" is now running
    for i in range(10):
        w.submit("a", lambda i=i: ran.append(i))
    w.submit("b", lambda: 1 / 0)
    gate.set()
    assert w.wait_idle(5)
    assert ran == ["first", 9]  # intermediate values dropped, the latest ran
    assert errors == ["b"]
    w.submit("a", lambda: ran.append("after"))
    assert w.wait_idle(5) and ran[-1] == "after"
    w.stop()


def test_state_session_round_trip():
    st = AppState()
    st.gamma, st.lines, st.seed_frame, st.seed_base = (
        0.7,
        [[(1.0, 2.0), (3.0, 4.0), (5.5, 6.0)]],
        (1.5, 2.5),
        (10.0, 20.0),
    )
    st.points = {"P1": {0: (1.0, 2.0), 3: (4.0, 5.0)}}
    st.mode = "Seed"
    data = json.loads(json.dumps(st.to_session()))
    st2 = AppState()
    st2.apply_session(data)
    assert st2.to_session() == st.to_session() and st2.seed == (1.5, 2.5, 10.0, 20.0)
    st3 = AppState()
    st3.apply_session({"gamma": "nonsense", "mode": "Nope", "seq_frame": 4})
    assert st3.gamma == 0.0 and st3.mode == "Calibrate" and st3.seq_frame == 4


def test_write_atomic_leaves_no_temporary(tmp_path):
    write_atomic(tmp_path / "a.json", "{}")
    write_atomic(tmp_path / "a.json", '{"x": 1}')
    assert json.loads((tmp_path / "a.json").read_text()) == {"x": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_viz_blend_checkerboard_colorize_exact():
    a = np.full((4, 4, 3), 200, np.uint8)
    b = np.full((4, 4, 3), 100, np.uint8)
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False
    out = viz.blend(a, b, 0.5, mask=mask)
    assert out[1, 1, 0] == 150 and out[0, 0, 0] == 100
    cb = viz.checkerboard(a, b, tile=2)
    assert cb[0, 0, 0] == 200 and cb[0, 2, 0] == 100 and cb[2, 2, 0] == 200
    rgba = viz.colorize(np.array([[0.0, np.nan], [1.0, 0.5]]), 0.0, 1.0, alpha=99)
    assert rgba.shape == (2, 2, 4) and rgba[0, 1, 3] == 0 and rgba[0, 0, 3] == 99
    assert not np.array_equal(rgba[0, 0, :3], rgba[1, 0, :3])
    img, vmax = viz.field_cells_image(
        np.array([[[3.0, 4.0], [0.0, 0.0]]]), np.array([[True, False]])
    )
    assert vmax == pytest.approx(5.0) and img[0, 1, 3] == 0
    plot, (x0, x1) = viz.series_plot([1.0, np.nan, 3.0], flagged=[False, False, True], current=1)
    assert plot.shape == (160, 640, 3) and 0 < x0 < x1 < 640
    assert viz.colorbar(0, 2.5, label="px").shape == (56, 320, 3)
    with pytest.raises(ValueError, match="alpha"):
        viz.blend(a, b, 1.5)
    with pytest.raises(ValueError, match="differ in shape"):
        viz.checkerboard(a, b[:2])


# ---------------------------------------------------------------- the app in process


def seed_at_truth(app, truth, fxy=(320.0, 240.0)):
    """Place pair 1 at a raw frame point and its true map position (the fit runs by itself)."""
    seed = app.views["Seed"]
    fxy = np.asarray(fxy, float)
    bxy = truth.frame_to_base(app.state.reference_frame, fxy[None])[0]
    w, h = app.inputs.frame_size
    corrected = HarrisModel(truth.gamma, w, h).corrected_from_raw(fxy[None])[0]
    click(app, seed.scene.planes["frame"], corrected)
    click(app, seed.scene.planes["base"], bxy)
    app.jobs.join(120)
    app.worker.wait_idle()
    return bxy


def true_heading(truth, k: int, fxy) -> tuple[float, float]:
    """The truth's heading (degrees in [0, 360), clockwise on screen) and scale (map px per
    corrected frame px) at raw frame point ``fxy`` of frame ``k``: the local similarity there."""
    w, h = truth.frame_size
    harris = HarrisModel(truth.gamma, w, h)
    c = harris.corrected_from_raw(np.array([fxy], float))[0]
    q = truth.frame_to_base(k, harris.raw_from_corrected(np.array([c, c + (1.0, 0.0)])))
    d = q[1] - q[0]
    return float(np.degrees(np.arctan2(d[1], d[0])) % 360.0), float(np.hypot(*d))


def heading_shown(text: str, where: str = "Coarse step") -> float | None:
    """The heading a line of the Seed view's heading text shows (None when absent)."""
    import re

    m = re.search(where + r"[^\n]*?heading \*{0,2}([0-9.]+)°", text)
    return float(m.group(1)) if m else None


def angle_gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


@pytest.fixture
def fitted(tmp_path, small_seq, make_app):
    """An app with γ set, the reference frame seeded and fitted (coarse + fine)."""
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Seed")
    bxy = seed_at_truth(app, truth)
    ref = app.state.reference
    assert ref is not None and ref.coarse and ref.fine, app.errors
    return app, truth, bxy


@pytest.fixture
def registered(fitted):
    """``fitted`` plus the whole sequence registered."""
    app, truth, bxy = fitted
    app.set_mode("Sequence")
    assert app.views["Sequence"].run()
    app.jobs.join(300)
    app.worker.wait_idle()
    r = app.state.result
    assert r is not None and all(rec.status == "ok" for rec in r.records), app.errors
    return app, truth, bxy


def test_calibrate_gamma_lines_and_restore(tmp_path, small_seq, make_app):
    from registration.lens import load_lines

    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    cal = app.views["Calibrate"]
    assert app.shown["Calibrate"] == (0, 0.0, 640, 480)
    assert not app.state.steps()["calibrated"]
    cal.panel.gamma_slider.value = 0.5
    app.worker.wait_idle()
    assert app.state.gamma == 0.5 and cal.panel.gamma_number.value == 0.5
    assert app.shown["Calibrate"][:2] == (0, 0.5) and app.state.steps()["calibrated"]
    cal.panel.gamma_number.value = 0.6123
    app.worker.wait_idle()
    assert app.state.gamma == pytest.approx(0.6123)
    assert cal.panel.gamma_slider.value == pytest.approx(0.61)
    assert json.loads((proj / "project.json").read_text())["gamma"] == pytest.approx(0.6123)
    # An invalid γ (beyond the Harris validity limit) is refused and the old one kept.
    cal.panel.gamma_number.value = 3.0
    app.worker.wait_idle()
    assert app.state.gamma == pytest.approx(0.6123) and "Invalid γ" in app.errors[-1]
    # Three clicks on the corrected image make a line stored in RAW pixels.
    clicked = np.array([[60.0, 40.0], [160.0, 60.0], [250.0, 80.0]])
    for xy in clicked:
        assert click(app, cal.scene.planes["frame"], xy)[0] == "frame"
    cal.finish_line()
    app.worker.wait_idle()
    model = HarrisModel(0.6123, 640, 480)
    raw = np.array(app.state.lines[0])
    assert np.allclose(model.corrected_from_raw(raw), clicked, atol=1e-6)
    saved = load_lines(proj / "LINES.json")
    assert saved.image_size == (640, 480) and np.allclose(saved.lines[0], raw)
    assert "Overall" in cal.panel.lines_md.content  # straightness shown
    # A click outside the image does nothing.
    o, d = cal.scene.planes["frame"].geom.ray_towards_pixel((-20.0, 10.0), CAMERA)
    assert app.handle_click(o, d) is None
    app.stop()
    # Restarting on the same project restores γ and lines.
    app2 = make_app(proj, small_seq)
    assert app2.state.gamma == pytest.approx(0.6123) and app2.state.steps()["calibrated"]
    assert np.allclose(np.array(app2.state.lines[0]), raw)
    assert app2.views["Calibrate"].panel.gamma_number.value == pytest.approx(0.6123)


def test_straightness_table_follows_gamma(tmp_path, small_seq, make_app):
    """The per-line straightness table is recomputed for each γ shown (it never followed γ)."""
    app = make_app(tmp_path / "proj", small_seq)
    cal = app.views["Calibrate"]
    # A line straight in the RAW frame is straight at γ = 0 and bent once corrected.
    for xy in ([40.0, 60.0], [320.0, 50.0], [600.0, 60.0]):
        click(app, cal.scene.planes["frame"], xy)
    cal.finish_line()
    app.worker.wait_idle()
    at0 = cal.panel.lines_md.content
    cal.set_gamma(0.6)
    app.worker.wait_idle()
    at6 = cal.panel.lines_md.content
    per0 = cal.scores()
    assert at0 != at6
    expected = f"{cal.scores()[1]:.2f} px"
    assert expected in at6, (expected, at6)
    cal.set_gamma(0.0)
    app.worker.wait_idle()
    assert cal.panel.lines_md.content == at0 and per0 != cal.scores()


def test_seed_clicks_are_raw_pixels_replace_and_undo(tmp_path, small_seq, make_app):
    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    app.views["Calibrate"].panel.gamma_number.value = 0.7
    app.set_mode("Seed")
    app.worker.wait_idle()
    seed = app.views["Seed"]
    seed.panel.auto_fit.value = False
    assert click(app, seed.scene.planes["frame"], (100.25, 80.75))[0] == "frame"
    assert click(app, seed.scene.planes["base"], (300.5, 250.0))[0] == "base"
    assert click(app, seed.scene.planes["base"], (310.0, 260.0))[0] == "base"  # replaces
    fx, fy, bx, by = app.state.seed
    corrected = HarrisModel(0.7, 640, 480).corrected_from_raw([(fx, fy)])[0]
    assert np.allclose(corrected, (100.25, 80.75), atol=1e-6)
    assert (bx, by) == pytest.approx((310.0, 260.0), abs=1e-6)
    saved = json.loads((proj / "project.json").read_text())
    assert saved["seed_base"] == pytest.approx([310.0, 260.0]) and saved["mode"] == "Seed"
    # The frame is drawn as tall as the map, and both markers are on screen.
    app.worker.wait_idle()
    fg, bg = seed.scene.planes["frame"].geom, seed.scene.planes["base"].geom
    assert fg.render_size[1] == pytest.approx(bg.render_size[1])
    assert set(seed.scene.markers) == {("frame", 1), ("base", 1)}
    # Undo takes back the last click, then the one before.
    seed.undo()
    assert app.state.seed_base == pytest.approx((300.5, 250.0))
    seed.undo()
    assert app.state.seed_base is None and app.state.seed_frame is not None
    # A second pair: heading and scale from the two pairs are shown at once.
    click(app, seed.scene.planes["base"], (300.0, 250.0))
    seed.set_pair(2)
    click(app, seed.scene.planes["frame"], (400.0, 80.75))
    click(app, seed.scene.planes["base"], (600.0, 250.0))
    assert app.state.seed2 is not None
    assert "heading **0.0°**" in seed.panel.heading_md.content, seed.panel.heading_md.content
    assert "fixed by the two pairs" in seed.panel.heading_md.content
    seed.clear_seed()
    assert app.state.seed is None and app.state.seed2 is None


@pytest.mark.slow
def test_seed_heading_typed_correction_and_failure_reason(tmp_path, small_seq, make_app):
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Seed")
    seed = app.views["Seed"]
    seed.panel.auto_fit.value = False  # coarse steps only, run below

    def coarse():
        assert seed.run_fit(None, fine=False)
        app.jobs.join(120)
        app.worker.wait_idle()
        return app.state.current_reference().coarse

    fxy = (320.0, 240.0)
    bxy = truth.frame_to_base(0, np.array([fxy]))[0]
    seed.place_seed("frame", fxy)
    seed.place_seed("base", tuple(bxy))
    c = coarse()
    # After one click: the heading and scale the library estimated, labelled as such, and the
    # correction boxes start from them.
    want, scale = true_heading(truth, 0, fxy)
    text = seed.panel.heading_md.content
    assert c and "estimated from the click" in text, text
    confirm = c.image_agreement
    assert f"{confirm.agreeing} of {confirm.matched} map templates agree" in text, text
    assert confirm.agreeing > 0.5 * confirm.matched, confirm
    assert angle_gap(heading_shown(text), want) < 5.0
    assert seed.panel.heading_in.value == pytest.approx(c.heading_deg % 360, abs=0.06)
    assert seed.panel.scale_in.value == pytest.approx(c.scale, abs=1e-4)
    # A typed heading and scale become pair 2 (100 px away) and reach the library exactly.
    assert seed.use_typed(want + 3.0, 1.1 * scale)
    assert app.state.seed2_typed == pytest.approx((want + 3.0, 1.1 * scale))
    f2 = np.array(app.state.seed2_frame)
    harris = HarrisModel(truth.gamma, *truth.frame_size)
    c1, c2 = harris.corrected_from_raw(np.array([fxy, f2]))
    assert np.hypot(*(c2 - c1)) == pytest.approx(100.0, abs=1e-6)
    assert "(typed)" in seed.panel.seed_md.content
    c = coarse()
    assert c.gate == "two seeds" and c.heading_deg == pytest.approx((want + 3.0) % 360, abs=1e-6)
    assert c.scale == pytest.approx(1.1 * scale, rel=1e-9)
    assert heading_shown(seed.panel.heading_md.content) == pytest.approx(
        (want + 3.0) % 360, abs=0.06
    )
    # Pair 2 follows pair 1 while the typed values hold; placing pair 2 by hand ends them.
    b2 = np.array(app.state.seed2_base)
    seed.place_seed("base", tuple(bxy + (4.0, -2.0)), pair=1)
    assert np.array(app.state.seed2_base) == pytest.approx(b2 + (4.0, -2.0), abs=1e-9)
    hp = heading_shown(seed.panel.heading_md.content, "Pairs")
    assert hp == pytest.approx((want + 3.0) % 360, abs=0.06)
    seed.place_seed("base", tuple(np.array(app.state.seed2_base) + (0.0, 30.0)), pair=2)
    assert app.state.seed2_typed is None and "(typed)" not in seed.panel.seed_md.content
    # A click that contradicts the registration found: the reason, prominently.
    seed.clear_pair2()
    seed.place_seed("base", tuple(bxy + (150.0, 0.0)), pair=1)
    c = coarse()
    assert not c and "check the click" in c.reason
    assert "Coarse step failed" in seed.panel.alert.content
    assert "check the click" in seed.panel.alert.content
    # The saved fit keeps what the panel shows (heading, gate outline) across a restart.
    from app.gui.project import REFERENCE_FILE, reference_from_file

    seed.place_seed("base", tuple(bxy), pair=1)
    good = coarse()
    _, back, _ = reference_from_file(app.project.folder / REFERENCE_FILE)
    assert back.heading_deg == pytest.approx(good.heading_deg) and back.gate == "seed"
    assert np.allclose(back.gate_outline_base, good.gate_outline_base)


def test_seed_drop_moves_the_fit(fitted):
    """Dropping a dragged map marker elsewhere moves the seed and re-runs the fit."""
    app, truth, bxy = fitted
    seed = app.views["Seed"]
    before = app.state.reference
    b0 = before.coarse.base_from_corrected.apply(before.coarse.frame_xy[:1])
    seed.on_drop("base", 1, bxy + (6.0, -4.0))
    app.worker.wait_idle()
    app.jobs.join(120)
    app.worker.wait_idle()
    assert app.state.seed_base == pytest.approx(tuple(bxy + (6.0, -4.0)))
    after = app.state.reference
    assert after is not before and after.key["seed"][2:] == pytest.approx(list(bxy + (6.0, -4.0)))
    assert after.coarse and after.fine
    # The drop can be undone, which brings the earlier seed back.
    seed.undo()
    assert app.state.seed_base == pytest.approx(tuple(bxy))
    assert np.isfinite(b0).all()


def test_control_points_disable_worst_manual_and_export(fitted):
    from registration.gis import read_points_file

    app, truth, bxy = fitted
    seed = app.views["Seed"]
    t0 = seed.table
    assert t0 is not None and t0.n_enabled == int(app.state.reference.fine_auto.kept.sum())
    rms0 = t0.rms
    assert f"{rms0:.3f} px" in seed.panel.cps.summary.content
    worst = seed.disable_worst()
    app.worker.wait_idle()
    t1 = seed.table
    assert not t1.enabled[t1.row(worst)] and t1.n_enabled == t0.n_enabled - 1
    assert t1.rms < rms0 and f"{t1.rms:.3f} px" in seed.panel.cps.summary.content
    # The run uses the re-fitted model.
    assert app.state.reference.fine.base_from_corrected is t1.model
    # Selecting a row highlights it and centres the magnifier on it.
    seed.select_point(int(t1.ids[5]))
    app.worker.wait_idle()
    assert seed.selected == int(t1.ids[5]) and 'class="selected' in seed.panel.cps.table.content
    # A manual point at the true position of a frame point joins the fit.
    w, h = app.inputs.frame_size
    fxy = np.array([[200.0, 150.0]])
    seed.points.toggle_manual()
    corrected = HarrisModel(truth.gamma, w, h).corrected_from_raw(fxy)[0]
    click(app, seed.scene.planes["frame"], corrected)
    click(app, seed.scene.planes["base"], truth.frame_to_base(0, fxy)[0])
    app.worker.wait_idle()
    t2 = seed.table
    assert "manual" in t2.source and t2.n_enabled == t1.n_enabled + 1
    assert t2.residual[t2.source.index("manual")] < 2.0
    # Undo removes the manual point again.
    seed.undo()
    app.worker.wait_idle()
    assert "manual" not in seed.table.source
    # The map side typed instead of clicked (a plain base: base px); outside the map: refused.
    bxy = truth.frame_to_base(0, fxy)[0]
    assert not seed.points.typed_map_point(*bxy)  # no frame point yet
    seed.points.toggle_manual()
    click(app, seed.scene.planes["frame"], corrected)
    assert not seed.points.typed_map_point(-50.0, 10.0)
    assert "outside the" in app.notices[-1][1]
    assert seed.points.typed_map_point(*bxy)
    app.worker.wait_idle()
    assert np.allclose(app.state.cp_edits.manual[-1][2:], bxy)
    assert "manual" in seed.table.source
    seed.undo()
    app.worker.wait_idle()
    # Export as QGIS .points: the header, and raw (x, y) -> (x + 0.5, -(y + 0.5)).
    assert seed.export_points()
    path = next(app.project.folder.glob("reference_frame_*.points"))
    assert path.read_text().splitlines()[0] == "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"
    pts = read_points_file(path)
    t = seed.table
    assert len(pts["map"]) == len(t.ids) and pts["crs"] is None  # a plain base: no CRS
    assert np.allclose(pts["source"], t.frame_xy, atol=1e-9)
    # The map side of a plain base: its pixels in the same corner/y-up convention.
    assert np.allclose(pts["map"], t.base_xy * (1, -1) + (0.5, -0.5), atol=1e-9)
    assert int(pts["enable"].sum()) == t.n_enabled


def test_control_points_import_from_a_qgis_points_file(fitted):
    """A QGIS ``.points`` file of the reference frame (three points at the truth, one
    disabled) joins the fit as manual points, enabled as the file says, undoably; a file in a
    map CRS for a plain base, or with a point outside the frame, is refused in one line and
    changes nothing."""
    from registration.gis import write_points_file

    app, truth, bxy = fitted
    seed = app.views["Seed"]
    n0 = len(seed.table.ids)
    fxy = np.array([[200.0, 150.0], [420.0, 300.0], [320.0, 100.0]])
    base = truth.frame_to_base(0, fxy)
    plain = base * (1, -1) + (0.5, -0.5)  # QGIS's corner/y-up pixels of a plain base
    path = write_points_file(
        app.project.folder / "mine.points", fxy, plain, crs_wkt=None,
        enabled=np.array([True, False, True]),
    )  # fmt: skip
    assert seed.points.import_points("mine.points", path.read_bytes())
    app.worker.wait_idle()
    t = seed.table
    assert len(t.ids) == n0 + 3 and t.source[-3:] == ["manual"] * 3
    assert np.allclose(np.array(app.state.cp_edits.manual), np.c_[fxy, base], atol=1e-9)
    assert list(t.enabled[-3:]) == [True, False, True]
    assert np.all(t.residual[-3:] < 2.0)  # at the truth: the fit agrees
    assert "3 manual points from mine.points (1 disabled)" in app.notices[-1][1]
    seed.undo()
    app.worker.wait_idle()
    assert len(seed.table.ids) == n0 and not app.state.cp_edits.manual
    bad = [
        (write_points_file(
            app.project.folder / "geo.points", fxy, plain, crs_wkt="EPSG:32633"
        ), "its map coordinates are in WGS 84 / UTM zone 33N, and the base map has no "
           "georeference"),
        (write_points_file(
            app.project.folder / "off.points", fxy + (0, 400), plain, crs_wkt=None
        ), "off.points point 1: its frame point (200.0, 550.0) is outside the 640x480 frame"),
    ]  # fmt: skip
    for p, message in bad:
        assert not seed.points.import_points(p.name, p.read_bytes())
        assert message in app.notices[-1][1] and "\n" not in app.notices[-1][1]
    app.worker.wait_idle()
    assert len(seed.table.ids) == n0 and not app.state.cp_edits.manual


def test_review_inliers_only_by_default_and_screen_sized(fitted):
    """Match lines: a sample of at most the chosen count, spread over the frame, only between
    points on the images shown, with the counts said; a toggle hides them."""
    from app.gui.views.seed.view import inside

    app, truth, bxy = fitted
    seed = app.views["Seed"]
    coarse = app.state.reference.coarse
    fp, bp = seed.scene.planes["frame"].geom, seed.scene.planes["base"].geom
    shown = coarse.inliers & inside(coarse.frame_xy, fp) & inside(coarse.base_xy, bp)
    lines = seed.scene.match_lines
    n = len(lines.points)
    assert lines is not None and n == min(150, int(shown.sum())) and coarse.n_inliers > 150
    md = seed.panel.review_md.content
    assert f"**{coarse.n_inliers}** inlier matches of {coarse.n_matches}" in md
    assert f"lines drawn for {n} of them" in md
    # Every line starts and ends on the images (the segments' ends in world units).
    ends = np.asarray(lines.points, float)
    assert inside(fp.pixel_from_world(ends[:, 0])[:, :2], fp).all()
    assert inside(bp.pixel_from_world(ends[:, 1])[:, :2], bp).all()
    # Spread over the frame: each quarter of it has lines.
    quarter = fp.pixel_from_world(ends[:, 0])[:, :2] // (np.array([fp.width, fp.height]) / 2)
    assert len({tuple(q) for q in quarter.astype(int)}) == 4
    seed.panel.max_lines.value = 40
    app.worker.wait_idle()
    assert len(seed.scene.match_lines.points) <= 40
    seed.panel.show_match_lines.value = False
    app.worker.wait_idle()
    assert seed.scene.match_lines is None and "match lines hidden" in seed.panel.review_md.content
    seed.panel.show_match_lines.value = True
    seed.panel.max_lines.value = 1000
    seed.panel.show_outliers.value = True
    app.worker.wait_idle()
    gated = coarse.gated & inside(coarse.frame_xy, fp) & inside(coarse.base_xy, bp)
    assert len(seed.scene.match_lines.points) == min(1000, int(gated.sum()))
    # Dots keep their screen size: zooming in by 4 shrinks them 4x in world units.
    dots = seed.scene.planes["base"].overlay("cps")
    size0 = dots.point_size
    app.camera_moved(-2.0, np.deg2rad(60), 800)
    app.worker.wait_idle()
    size1 = seed.scene.planes["base"].overlay("cps").point_size
    app.camera_moved(-0.5, np.deg2rad(60), 800)
    app.worker.wait_idle()
    size2 = seed.scene.planes["base"].overlay("cps").point_size
    assert size0 > 0 and size2 == pytest.approx(size1 / 4)
    # Residual vectors are scaled automatically (90th percentile ~3 % of the map's width).
    t = seed.table
    bw = seed.scene.planes["base"].geom.width
    drawn = seed.vector_scale_used * np.percentile(t.residual[t.enabled], 90)
    assert 0.01 * bw < drawn < 0.06 * bw
    # The gate is drawn, clipped to the map.
    gate = seed.scene.planes["base"].overlay("gate")
    assert gate is not None
    pix = seed.scene.planes["base"].geom.pixel_from_world(np.asarray(gate.points, float))
    assert pix.min() >= -0.6 and (pix[..., 0] <= bw).all()


def test_the_magnifier_shows_corner_points():
    """A control point in the frame's corner lies, corrected (γ 0.7), outside a corrected image
    of the frame's size: the magnifier resamples the raw frame there instead of showing grey."""
    from app.gui.views.seed.scene import magnifier_crop, magnifier_crop_corrected, magnifier_side
    from registration.lens import Camera

    yy, xx = np.mgrid[0:480, 0:640]
    raw = np.dstack([xx * 0.3, yy * 0.4, np.full_like(xx, 100)]).astype(np.uint8)
    camera = Camera(0.7, 640, 480)
    corner = np.array([[3.0, 4.0]])
    fxy = camera.corrected_from_raw(corner)[0]
    assert fxy.min() < 0  # outside the corrected image of the frame's size
    old = magnifier_crop(camera.undistort(raw), fxy, (255, 0, 0))
    new = magnifier_crop_corrected(raw, camera, fxy, (255, 0, 0))
    c = magnifier_side() // 2
    assert (old[c + 10, c + 10] == 225).all()  # the old magnifier: grey
    # The new one: the raw frame's value where that magnifier pixel lies in the raw frame.
    offset = 10 / 3.0  # 10 magnifier px at its zoom of 3
    q = camera.raw_from_corrected(fxy[None] + 0.5 + offset)[0]
    assert np.allclose(new[c + 10, c + 10, :2], (q[0] * 0.3, q[1] * 0.4), atol=1.0)


def test_sequence_plot_jump_failed_list_and_rerun(registered):
    app, truth, bxy = registered
    seq = app.views["Sequence"]
    # The chart's x values are the frames, its RMS series the records'.
    data = seq.panel.plot.data
    assert np.array_equal(data[0], np.arange(4.0))
    assert np.allclose(data[1], seq.error_values(), equal_nan=True)
    # A click on the chart (the browser script sends the hovered frame) shows that frame.
    assert app.events.dispatch(json.dumps({"kind": "plot-frame", "value": 2, "n": 1}))
    app.worker.wait_idle()
    assert app.state.seq_frame == 2 and app.shown["Sequence"][0] == 2
    assert data is not seq.panel.plot.data and seq.panel.plot.data[4][2] == pytest.approx(
        seq.error_values()[2]
    )
    # Frame 0 shows its stage times, not a zero total.
    seq.set_frame(0)
    app.worker.wait_idle()
    assert (
        "time 0.00 s" not in seq.panel.frame_md.content and "coarse" in seq.panel.frame_md.content
    )
    # Register frame 2 again: its record is rewritten, the others are left alone.
    frames = app.project.result_dir / "frames"
    mtimes = {p.name: p.stat().st_mtime_ns for p in frames.glob("*.json")}
    seq.set_frame(2)
    assert seq.rerun_frame()
    app.jobs.join(120)
    app.worker.wait_idle()
    after = {p.name: p.stat().st_mtime_ns for p in frames.glob("*.json")}
    assert after["000002.json"] != mtimes["000002.json"]
    assert all(after[n] == m for n, m in mtimes.items() if n != "000002.json")
    assert app.state.result.is_ok(2)
    # A failed frame is listed with its reason and can be jumped to.
    from registration.run import records as run_records

    rec = run_records.frame_record_path(app.project.result_dir, 3, ".json")
    rec.write_text(
        json.dumps({"k": 3, "status": "failed", "reason": "too few matches <b>", "stats": {}})
    )
    seq.load_result(app.project.result_dir)
    seq.refresh_text()
    assert "too few matches &lt;b&gt;" in seq.panel.failed_html.content
    seq.jump_to_next_failed()
    assert app.state.seq_frame == 3
    # The frame's control points (read-only) are listed for the frame shown.
    seq.set_frame(1)
    app.worker.wait_idle()
    assert (
        seq.table is not None
        and seq.table_frame == 1
        and "Read-only" in seq.panel.cps.summary.content
    )


def test_sequence_adjusted_together_shows_predicted_errors(fitted):
    """With "Adjust the frames together" (Seed view, Run settings), the run adjusts the
    sequence: the chart draws each frame's predicted error, the frame's line says it, the
    project remembers the choice."""
    app, truth, bxy = fitted
    app.views["Seed"].set_setting("adjust", True)
    assert json.loads((app.project.folder / "project.json").read_text())["adjust"] is True
    app.set_mode("Sequence")
    seq = app.views["Sequence"]
    assert "frames adjusted together on" in seq.run_text()[1]
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    r = app.state.result
    assert all(r.is_adjusted(k) for k in range(r.n_frames)), app.errors
    seq.draw_plot()
    predicted = seq.panel.plot.data[5]
    expected = [r.records[k].stats["adjustment"]["predicted_error_px"] for k in range(r.n_frames)]
    assert np.allclose(predicted[: r.n_frames], expected)
    seq.set_frame(1)
    app.worker.wait_idle()
    # The frame's line gives its own record's figures, not just their names.
    adj = r.records[1].stats["adjustment"]
    # Frame 1 is an intra-sensor frame: its control points are on the mid base image and the
    # previous frame, not on the map.
    assert r.records[1].stage == "intra-sensor"
    assert (
        f"predicted error {adj['predicted_error_px']:.2f} base px, {adj['n_links']} link points, "
        f"{adj['n_controls']} control points on the mid base image and the previous frame"
        in seq.panel.frame_md.content
    )
    assert "flagged" not in seq.panel.frame_md.content


def test_sequence_map_point_on_a_frame_and_solve_again(registered):
    """The analyst adds a map point on frame 2: a click on a feature of the frame drawn over
    the map, then a click where it lies on the map. The frames it touches are adjusted again
    with it (*Solve again*); the frame's line, the panel and the chart say so; removing it and
    solving again leaves no trace of it."""
    from registration.run.map_points import read_map_points

    app, truth, bxy = registered
    seq = app.views["Sequence"]
    tool, panel = seq.map_points, seq.panel.map_points
    seq.set_frame(0)
    app.worker.wait_idle()
    assert "registered to the map (the reference frame)" in seq.panel.frame_md.content
    assert not tool.start()  # the reference frame is fitted in the Seed view
    seq.set_frame(2)
    app.worker.wait_idle()
    r = app.state.result
    assert r.is_adjusted(2)
    fxy = np.array([[250.0, 200.0]])
    drawn = r.frame_to_base(2, fxy, "local")[0]  # where the registration draws that pixel
    true = truth.frame_to_base(2, fxy)[0]
    base = seq.scene.planes["base"]
    assert tool.start()
    assert "Click the feature in the frame" in panel.status_md.content and panel.btn_cancel.visible
    click(app, base, drawn)
    assert "Now click where it lies on the map" in panel.status_md.content
    click(app, base, true)
    assert app.jobs.join(60)
    app.worker.wait_idle()
    (point,) = read_map_points(app.project.result_dir)
    assert point.k == 2
    assert np.allclose(point.frame_xy, fxy[0], atol=0.01)
    assert np.allclose(point.base_xy, true, atol=0.01)
    assert not app.state.result.is_adjusted(2)
    assert "not adjusted with them yet" in panel.status_md.content
    assert tool.solve()
    assert app.jobs.join(300)
    app.worker.wait_idle()
    r = app.state.result
    assert all(r.is_adjusted(k) for k in range(r.n_frames)), app.errors
    adj = r.records[2].stats["adjustment"]
    assert adj["n_map_points"] == 1 and adj["map_point_rms_px"] < 1.0
    assert "1 map point of the analyst's" in seq.panel.frame_md.content
    assert "base px from them after the adjustment" in panel.status_md.content
    seq.draw_plot()
    on_map = seq.panel.plot.data[6]  # the reference frame and the frame with the map point
    assert np.isfinite(on_map[[0, 2]]).all() and np.isnan(on_map[[1, 3]]).all()
    # Removed, and solved again: no trace.
    assert tool.remove()
    assert app.jobs.join(60)
    assert read_map_points(app.project.result_dir) == []
    assert tool.solve()
    assert app.jobs.join(300)
    app.worker.wait_idle()
    assert "n_map_points" not in app.state.result.records[2].stats["adjustment"]


def test_sequence_text_follows_the_seed(tmp_path, small_seq, make_app):
    """The Sequence view no longer says "no seed" after a seed was set elsewhere."""
    app = make_app(tmp_path / "proj", small_seq)
    seq, seed = app.views["Sequence"], app.views["Seed"]
    seed.panel.auto_fit.value = False
    assert "no seed" in seq.panel.run_md.content
    app.set_mode("Seed")
    click(app, seed.scene.planes["frame"], (100.0, 100.0))
    click(app, seed.scene.planes["base"], (300.0, 300.0))
    assert "no seed" not in seq.panel.run_md.content and "seeded" in seq.panel.run_md.content
    assert "✓ seeded" in app.header.steps_md.content and "▶ Seed" in app.header.mode_buttons.options


def test_evaluate_pending_proposals_count_nowhere(registered):
    """Suggested points and refined proposals are pending until confirmed; a proposal left at
    the registration's prediction (an edge) cannot be confirmed; Table 2 counts only confirmed
    marks."""
    from registration.evaluation import read_points_csv

    app, truth, _ = registered
    app.set_mode("Evaluate")
    ev = app.views["Evaluate"]
    ev.set_frame(0)
    assert ev.suggest()
    app.jobs.join(120)
    app.worker.wait_idle()
    suggested = sorted(p for (p, k) in app.state.pending if k == 0)
    assert "NW" in suggested, app.errors
    assert "suggested: a corner seen in" in ev.panel.marks_html.content
    ev.set_point("NW")
    assert ev.confirm()
    nw0 = np.array([app.state.points["NW"][0]])
    # Frame 1 is confirmed by a click at the truth; frame 2 is proposed.
    ev.set_frame(1)
    click(app, ev.scene.planes["frame"], truth.base_to_frame(1, truth.frame_to_base(0, nw0))[0])
    assert ev.propose_next()
    app.worker.wait_idle()
    assert app.state.eval_frame == 2 and ("NW", 2) in app.state.pending
    mark = app.state.pending[("NW", 2)]
    assert mark.confirmable and np.isfinite(mark.offset_px), mark
    proposed = np.array(app.state.points["NW"][2])
    assert np.hypot(*(proposed - truth.base_to_frame(2, truth.frame_to_base(0, nw0))[0])) < 0.3
    # Shown as pending with its NCC score and its offset, left out of POINTS.csv and Table 2.
    assert f"proposed, NCC {mark.score:.2f}" in ev.panel.marks_html.content
    assert "<th>offset</th>" in ev.panel.marks_html.content
    marks = read_points_csv(app.project.points_path, 4, (640, 480))
    assert sorted(marks.marks["NW"]) == [0, 1]
    assert "# proposed, not confirmed" in app.project.points_path.read_text()
    assert ev.compute_table()
    app.jobs.join(60)
    report = app.state.report
    assert report.table.frames["NW"] == [1]
    assert "pending proposals left out" in ev.panel.table_md.content
    assert app.views["Evaluate"].panel.table_panel.visible
    # Confirmed, it counts.
    ev.set_point("NW")
    ev.set_frame(2)
    assert ev.confirm()
    assert ("NW", 2) not in app.state.pending
    assert ev.compute_table()
    app.jobs.join(60)
    assert app.state.report.table.frames["NW"] == [1, 2]
    # Each mark shows its residual (local stage, px from the reference position).
    res = ev.mark_residuals()
    assert res[("NW", 0)] == pytest.approx(0.0) and res[("NW", 2)] < 1.0
    # A point on an edge: the proposal stays at the prediction and cannot be confirmed.
    edge = _edge_point(app.inputs.frame(0))
    ev.new_point()
    name = app.state.point_name
    ev.set_frame(0)
    click(app, ev.scene.planes["frame"], edge)
    assert ev.propose_next()
    app.worker.wait_idle()
    mark = app.state.pending[(name, 1)]
    assert not mark.confirmable and "along an edge" in mark.note
    assert "predicted only (along an edge" in ev.panel.marks_html.content
    assert not ev.confirm() and (name, 1) in app.state.pending
    # Table 2 is downloadable (CSV and markdown) and saved.
    assert ev.download_table("csv") and ev.download_table("markdown")
    assert (app.project.folder / "TABLE2.csv").exists() and (
        app.project.folder / "TABLE2.md"
    ).exists()
    assert "✓ evaluated" in app.header.steps_md.content
    # The mean anchor is a control of the app (the library's hint names it).
    ev.panel.anchor.value = "mean"
    assert app.state.anchor == "mean"


def _edge_point(image) -> tuple[float, float]:
    """A point of ``image`` whose patch is a clean edge (strong texture one way only)."""
    import cv2

    from registration.evaluation import patch_structure

    grey = cv2.cvtColor(np.asarray(image), cv2.COLOR_RGB2GRAY)
    best = None
    for y in range(40, grey.shape[0] - 40, 4):
        for x in range(40, grey.shape[1] - 40, 4):
            s = patch_structure(grey[y - 15 : y + 16, x - 15 : x + 16])
            strength = s.texture**2 / max(s.isotropy, 1e-9)
            if s.isotropy < 0.03 and (best is None or strength > best[0]):
                best = (strength, (float(x), float(y)))
    assert best is not None
    return best[1]


def test_evaluate_marks_points(tmp_path, small_seq, make_app):
    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    app.set_mode("Evaluate")
    ev = app.views["Evaluate"]
    app.worker.wait_idle()
    click(app, ev.scene.planes["frame"], (50.0, 60.0))
    ev.panel.frame_slider.value = 2
    click(app, ev.scene.planes["frame"], (52.5, 61.0))
    ev.new_point()
    click(app, ev.scene.planes["frame"], (200.0, 100.0))
    pts = app.state.points
    assert sorted(pts) == ["NE", "NW"] and sorted(pts["NW"]) == [0, 2] and list(pts["NE"]) == [2]
    assert pts["NW"][0] == pytest.approx((50.0, 60.0), abs=1e-6)
    assert pts["NW"][2] == pytest.approx((52.5, 61.0), abs=1e-6)
    assert pts["NE"][2] == pytest.approx((200.0, 100.0), abs=1e-6)
    assert [r[:2] for r in ev.points_rows()] == [(0, "NW"), (2, "NW"), (2, "NE")]
    saved = json.loads((proj / "project.json").read_text())
    assert saved["points"]["NW"]["2"] == pytest.approx([52.5, 61.0], abs=1e-6)
    from registration.evaluation import read_points_csv

    marks = read_points_csv(proj / "POINTS.csv", 4, (640, 480), min_frames=1)
    assert marks.marks["NW"][2] == pytest.approx((52.5, 61.0), abs=1e-3)
    assert ev.export_csv()
    assert any(n[0] == "POINTS.csv" for n in app.notices)
    ev.delete_mark()
    assert "NE" not in app.state.points
    assert "NE" not in (proj / "POINTS.csv").read_text()


def test_demo_mode_builds_in_background(tmp_path, small_seq, make_app):
    calls = []

    def builder(progress=None):
        for i in range(5):
            progress(i + 1, 5)
        calls.append(1)
        return small_seq

    app = make_app(tmp_path / "proj", None, demo_builder=builder)
    app.jobs.join(30)
    app.worker.wait_idle()
    assert calls == [1] and app.inputs is not None and app.inputs.n_frames == 4
    assert app.shown["Calibrate"][0] == 0


def test_cli_rejects_half_inputs(capsys):
    from app.cli import main

    assert main(["app", "--frames", "x"]) == 2
    assert "go together" in capsys.readouterr().err


def test_estimate_gamma_from_clicked_lines_and_automatically(tmp_path, small_seq, make_app):
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    cal = app.views["Calibrate"]
    plane = cal.scene.planes["frame"]
    # Lines straight on the ground (straight in the base map), clicked where they appear in the
    # raw frame (γ = 0 shows the raw frame).
    centre = truth.frame_to_base(0, np.array([[320.0, 240.0]]))[0]
    t = np.linspace(-250, 250, 9)
    for dx, dy in ((1, 0), (0, 1), (1, 1)):
        for offset in (-150, 150):
            n = np.array([-dy, dx]) / np.hypot(dx, dy)
            base_pts = centre + offset * n + np.outer(t, [dx, dy]) / np.hypot(dx, dy)
            raw = truth.base_to_frame(0, base_pts)
            raw = raw[np.isfinite(raw).all(axis=1)]
            raw = raw[(raw[:, 0] > 5) & (raw[:, 0] < 634) & (raw[:, 1] > 5) & (raw[:, 1] < 474)]
            if len(raw) < 3:
                continue
            cal.new_line()
            for xy in raw:
                click(app, plane, xy)
            cal.finish_line()
    assert len(app.state.lines) >= 4
    g0 = app.state.gamma
    cal.estimate(auto=False)
    app.jobs.join(120)
    app.worker.wait_idle()
    # An estimate is shown beside the γ in use and replaces it only when the analyst accepts.
    assert app.state.gamma == g0 and cal.panel.btn_use_estimate.visible, app.errors
    assert "from lines" in cal.panel.estimate_md.content
    assert f"In use: γ = {g0:.4f}" in cal.panel.estimate_md.content
    assert cal.use_estimate()
    assert app.state.gamma == pytest.approx(truth.gamma, abs=0.05), app.errors
    assert not cal.panel.btn_use_estimate.visible
    assert "(estimated from lines)" in cal.panel.estimate_md.content
    # The residual-versus-γ chart marks the estimate (one point, at the curve's γ nearest it).
    grid, curve, marker = cal.panel.plot.data
    i = int(np.flatnonzero(np.isfinite(marker))[0])
    assert np.isfinite(marker).sum() == 1 and abs(grid[i] - app.state.gamma) <= np.diff(grid).max()
    assert json.loads(app.project.session_path.read_text())["gamma"] == pytest.approx(
        app.state.gamma
    )
    cal.set_gamma(0.0)
    cal.estimate(auto=True)
    app.jobs.join(180)
    app.worker.wait_idle()
    assert app.state.gamma == 0.0 and cal.use_estimate()
    assert app.state.gamma == pytest.approx(truth.gamma, abs=0.1), (
        app.errors,
        cal.panel.estimate_md.content,
    )
    # The lines the automatic estimate used are drawn on the image.
    assert cal.scene.planes["frame"].has("detected")


def test_frames_opened_without_gamma_take_the_estimate_the_cli_would(tmp_path, small_seq, make_app):
    """``aerialreg app`` (``auto_gamma``) on frames whose γ was never set runs the estimate
    from their motion and, when it passes ``--gamma auto``'s rule, uses it: one default for the
    app and the command line. On a flight without motion the estimate is not determined: γ
    stays unset and the analyst is told how to give it."""
    import shutil

    app = make_app(tmp_path / "proj", small_seq, auto_gamma=True)
    assert app.jobs.join(120)
    app.worker.wait_idle()
    # Measured 0.6977 ± 0.0083 (the simulator's camera: 0.7).
    assert app.state.gamma_set and abs(app.state.gamma - 0.7) < 0.02, app.notices[-3:]
    assert app.state.steps()["calibrated"]
    assert app.notices[-1][0] == "γ set from the frames' motion"
    cal = app.views["Calibrate"]
    assert "when the frames were opened" in cal.panel.estimate_md.content
    # A flight without motion: four copies of one frame.
    still = tmp_path / "still"
    (still / "frames").mkdir(parents=True)
    for k in range(4):
        shutil.copy(small_seq / "frames" / "000000.png", still / "frames" / f"{k:06d}.png")
    shutil.copy(small_seq / "base.png", still / "base.png")
    app2 = make_app(tmp_path / "proj2", still, auto_gamma=True)
    assert app2.jobs.join(120)
    app2.worker.wait_idle()
    assert not app2.state.gamma_set and app2.state.gamma == 0.0
    title, body = app2.notices[-1][:2]
    assert title == "γ not set" and "does not determine it" in body, app2.notices[-3:]
    assert "\n" not in body


def test_estimate_gamma_from_the_frames_motion(tmp_path, small_seq, make_app):
    """4 frames with a 0.04 s rolling shutter: the pairs are chosen from the frames' motion,
    the uncertainty covers the error, the chart marks the estimate, and the detected-lines
    overlay is not drawn for it."""
    import re

    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    cal = app.views["Calibrate"]
    cal.set_gamma(0.0)
    cal.estimate_from_motion()
    app.jobs.join(180)
    app.worker.wait_idle()
    assert app.state.gamma == 0.0 and cal.use_estimate()
    text = cal.panel.estimate_md.content
    m = re.search(r"from (\d) frame pairs (\d) apart.*matches in (\d) frame pairs", text)
    assert m and int(m[1]) >= 2 and int(m[3]) == int(m[1]), (app.errors, text)
    sigma = float(text.split("±")[1].split()[0])
    assert abs(app.state.gamma - truth.gamma) <= max(2 * sigma, 0.005), text
    assert abs(app.state.gamma - truth.gamma) <= 0.02, text
    grid, curve, marker = cal.panel.plot.data
    assert np.isfinite(marker).sum() == 1 and np.isfinite(curve).all()
    assert not cal.scene.planes["frame"].has("detected")


def cancel_after(view, n_reports: int) -> threading.Event:
    """Make ``view``'s next jobs press Cancel once they have reported progress ``n_reports``
    times (0: as they start), as the analyst would mid-job; the returned event is set when it
    was pressed."""
    pressed = threading.Event()
    real = view.ctx.run_job

    def run_job(name, fn, client=None, **kw):
        def wrapped(job):
            calls = []
            if n_reports == 0:  # pressed as the job starts
                pressed.set()
                job.cancel.set()

            class Spy:
                cancel = job.cancel

                def __call__(self, done, total=None, note=""):
                    job(done, total, note)
                    calls.append(done)
                    if len(calls) >= n_reports:
                        pressed.set()
                        job.cancel.set()

            fn(Spy())

        return real(name, wrapped, client, **kw)

    view.ctx.run_job = run_job
    return pressed


def test_cancelled_gamma_estimate_changes_nothing(tmp_path, small_seq, make_app):
    """Cancel stops the estimate from motion: γ and the last estimate stay as they were."""
    app = make_app(tmp_path / "proj", small_seq)
    cal = app.views["Calibrate"]
    cal.set_gamma(0.3)
    seen = cancel_after(cal, 2)  # after "choosing how many frames apart" and one frame pair
    cal.estimate_from_motion()
    app.jobs.join(180)
    app.worker.wait_idle()
    assert seen.is_set()
    assert app.state.gamma == 0.3 and cal.last_estimate is None
    assert not cal.panel.btn_use_estimate.visible


def test_cancelled_reference_fit_and_table2_change_nothing(registered):
    app, truth, _ = registered
    seed = app.views["Seed"]
    before = app.state.reference
    pressed = cancel_after(seed, 1)  # pressed while the coarse step runs
    assert seed.run_fit(fine=True)
    app.jobs.join(120)
    app.worker.wait_idle()
    assert pressed.is_set() and app.state.reference is before
    ev = app.views["Evaluate"]
    with app.state.lock:
        app.state.points["NW"] = {0: (100.0, 100.0), 1: (101.0, 100.0)}
    pressed = cancel_after(ev, 0)
    assert ev.compute_table()
    app.jobs.join(60)
    assert app.state.report is None


def test_a_changed_gamma_starts_afresh_and_the_earlier_result_can_be_restored(registered):
    """Registering with another γ keeps the old result as result.prev-1, says so in the app's
    words (no command-line options, no raw arrays); restoring it brings back the result and the
    γ it was made with, and keeps the newer one beside."""
    app, truth, _ = registered
    seq = app.views["Sequence"]
    folder = app.project.folder
    app.views["Calibrate"].set_gamma(truth.gamma + 0.01)
    app.set_mode("Sequence")
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    title, body, _ = next(n for n in app.notices if n[0] == "Starting a new result")
    assert "γ changed since the last result was made" in body and "result.prev-1" in body
    assert "--" not in body and "[" not in body and "Mismatch" not in body
    assert (folder / "result.prev-1").is_dir()
    assert app.state.result.gamma == pytest.approx(truth.gamma + 0.01)
    labels = seq.panel.earlier.options
    assert len(labels) == 1 and labels[0].startswith("result.prev-1: 4/4 frames ok, γ 0.7000")
    assert seq.earlier.restore(labels[0])
    app.jobs.join(60)
    app.worker.wait_idle()
    assert app.state.result.gamma == pytest.approx(truth.gamma)
    assert app.state.gamma == pytest.approx(truth.gamma) and not app.state.result_staleness()
    assert app.state.steps()["sequence registered"]
    assert (folder / "result.prev-2").is_dir() and not (folder / "result.prev-1").exists()
    assert seq.panel.earlier.options[0].startswith("result.prev-2: 4/4 frames ok, γ 0.7100")


def test_register_all_uses_the_control_points_the_analyst_edited(registered):
    """After a result exists, the analyst disables control points of the reference frame; the
    next *Register all frames* uses the edited fit (the old result is kept aside)."""
    app, truth, _ = registered
    seed, seq = app.views["Seed"], app.views["Sequence"]
    ref = app.state.reference_frame
    w, h = app.inputs.frame_size
    grid = np.stack(np.meshgrid(np.linspace(40, w - 40, 6), np.linspace(40, h - 40, 5)), -1)
    grid = grid.reshape(-1, 2)
    before = app.state.result.frame_to_base(ref, grid, "global")
    app.set_mode("Seed")
    for _ in range(8):
        seed.disable_worst()
        app.worker.wait_idle()
    edited = app.state.reference.fine.base_from_corrected
    camera = app.state.camera()
    want = edited.apply(camera.corrected_from_raw(grid))
    assert np.abs(want - before).max() > 0.02  # the edits move the fit
    app.set_mode("Sequence")
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    assert any("control points were edited" in n[1] for n in app.notices), app.notices
    assert (app.project.folder / "result.prev-1").is_dir()
    got = app.state.result.frame_to_base(ref, grid, "global")
    assert np.abs(got - want).max() < 0.01 < np.abs(got - before).max()


def test_a_result_made_with_another_gamma_is_stale(registered):
    app, truth, _ = registered
    assert app.state.steps()["sequence registered"]
    app.views["Calibrate"].set_gamma(truth.gamma + 0.02)
    app.update_header()
    steps = app.state.steps()
    assert not steps["sequence registered"] and not steps["reference registered"]
    text = app.header.steps_md.content
    assert "The registration result is stale" in text and "γ 0.7000, now 0.7200" in text
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.update_header()
    assert app.state.steps()["sequence registered"]
    assert "stale" not in app.header.steps_md.content


def test_sequence_cancel_resume_play_and_flicker(tmp_path, small_seq, make_app):
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Sequence")
    seq = app.views["Sequence"]
    records = app.project.result_dir / "frames"
    assert seq.run()
    # Cancel as soon as the first frame is written: the run stops after the frame in progress.
    t0 = time.monotonic()
    while not (records.is_dir() and any(records.glob("*.json"))) and time.monotonic() - t0 < 120:
        time.sleep(0.01)
    app.jobs.request_cancel()
    app.jobs.join(120)
    app.worker.wait_idle()
    statuses = [r.status for r in app.state.result.records]
    assert "pending" in statuses and statuses.count("ok") >= 1, statuses
    assert "Registration cancelled" in [n[0] for n in app.notices]

    def own(name):  # the frame's own registration (the adjustment adds to its record)
        rec = json.loads((records / name).read_text())
        return rec["model"], rec["stats"].get("time_s")

    done = {p.name: own(p.name) for p in records.glob("*.json")}
    # Running again resumes: finished frames are not redone.
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    assert all(r.status == "ok" for r in app.state.result.records), app.errors
    assert all(own(n) == m for n, m in done.items())
    # Play advances the scrubber, drawing frames from the smaller playback preview; pausing
    # stops it, and the frame it stops on is drawn again at the map preview's full size.
    from app.gui.views.sequence.view import PLAY_SIDE_FRACTION

    seq.set_frame(0)
    seq.panel.play.value = True
    t0 = time.monotonic()
    while app.state.seq_frame == 0 and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    sides = set()
    while app.state.seq_frame < 2 and time.monotonic() - t0 < 10:
        sides.add(app.shown["Sequence"][4])
        time.sleep(0.02)
    seq.panel.play.value = False
    assert app.state.seq_frame != 0
    assert int(PLAY_SIDE_FRACTION * app.display_max) in sides, sides
    time.sleep(0.5)
    app.worker.wait_idle()
    k = app.state.seq_frame
    time.sleep(1.0)
    assert app.state.seq_frame == k
    assert app.shown["Sequence"][0] == k and app.shown["Sequence"][4] == 2 * app.display_max
    # Flicker toggles the registered overlay on and off.
    seq.panel.overlay.value = "flicker"
    app.worker.wait_idle()
    seen = set()
    t0 = time.monotonic()
    while len(seen) < 2 and time.monotonic() - t0 < 5:
        seen.add(bool(seq.scene.planes["base"].overlay("registered").visible))
        time.sleep(0.05)
    assert seen == {True, False}


def test_one_project_per_opening(tmp_path, small_seq):
    """Starting on the demo and uploading both inputs makes exactly one new project, holding
    the uploads; the upload alone does not open anything."""
    data = tmp_path / "data"
    server = make_server("127.0.0.1", 0, verbose=False)
    from app.gui.project import default_project_dir

    app = App(
        server,
        Project(default_project_dir(None, None, data)),
        demo_builder=lambda progress=None: small_seq,
        project_is_explicit=False,
        data_dir=data,
    )
    try:
        app.start()
        app.jobs.join(30)
        app.worker.wait_idle()
        projects = data / "projects"
        assert len(list(projects.iterdir())) == 1

        class Up:
            def __init__(self, name, content):
                self.name, self.content = name, content

        frames_video = sorted((small_seq / "frames").iterdir())[0]
        app.handle_upload("base", Up("base.png", (small_seq / "base.png").read_bytes()), None)
        app.worker.wait_idle()
        assert len(list(projects.iterdir())) == 1  # nothing opened yet
        app.handle_upload("frames", Up("f.png", frames_video.read_bytes()), None)
        app.worker.wait_idle()
        assert len(list(projects.iterdir())) == 2, app.errors
        assert Path(app.inputs.base_path).parent == app.project.uploads_dir
        assert Path(app.inputs.frames_path).parent == app.project.uploads_dir
        demo_project = next(p for p in projects.iterdir() if p != app.project.folder)
        assert (
            not any((demo_project / "uploads").glob("*"))
            if (demo_project / "uploads").exists()
            else True
        )
    finally:
        app.stop()


def test_job_progress_reports_time_left():
    from app.gui.worker import Job

    seen = []
    job = Job("register", seen.append)
    t0 = time.monotonic()
    job(0, 10, "frames")
    assert job.eta_s is None and "left" not in job.describe()
    time.sleep(0.2)
    job(2, 10, "frames")
    t1 = time.monotonic()
    # 2 frames in ~0.2 s: 8 more take ~0.8 s.
    assert 4 * 0.2 * 0.9 <= job.eta_s <= 4 * (t1 - t0) * 1.1
    assert "register: 2/10 frames" in job.describe() and "left" in job.describe()
    assert len(seen) == 2 and job.fraction == pytest.approx(0.2)


def test_app_is_what_the_views_see(tmp_path, small_seq, make_app):
    """The app offers every member of the views' context protocol (views type against it and
    never import the server)."""
    from app.gui.context import ViewContext

    app = make_app(tmp_path / "proj", small_seq)
    members = [n for n in vars(ViewContext) if not n.startswith("_")]
    members += list(ViewContext.__annotations__)
    assert len(members) > 15 and [n for n in members if not hasattr(app, n)] == []
    assert all(view.ctx is app for view in app.views.values())


def test_nothing_is_written_while_the_state_lock_is_held(tmp_path, small_seq, monkeypatch):
    """Every file the app writes (project.json, LINES.json, POINTS.csv, ...) is written with the
    state's lock free: callbacks and the worker never wait for the disk."""
    from app.gui import project as project_module

    # A session that sets every view's widgets when the inputs open (their callbacks save).
    Project(tmp_path / "proj").save(
        {"overlay": "checkerboard", "opacity": 0.3, "stage": "global", "seq_frame": 2}
    )
    app = App(
        make_server("127.0.0.1", 0, verbose=False),
        Project(tmp_path / "proj"),
        frames=str(small_seq / "frames"),
        base=str(small_seq / "base.png"),
        allowed_dirs=[tmp_path, small_seq],
    )
    writes: list[tuple[str, bool]] = []
    write_atomic_ = project_module.write_atomic

    def watched(path, data):
        writes.append((Path(path).name, app.state.lock._is_owned()))
        write_atomic_(path, data)

    monkeypatch.setattr(project_module, "write_atomic", watched)
    try:
        app.start()
        _use_every_view(app)
    finally:
        app.stop()
    names = {name for name, _ in writes}
    assert {"project.json", "LINES.json", "POINTS.csv"} <= names, names
    assert [name for name, held in writes if held] == []


def _use_every_view(app) -> None:
    """Decisions in every view that save something (no fits: quick)."""
    app.worker.wait_idle()
    cal = app.views["Calibrate"]
    cal.panel.gamma_number.value = 0.7
    for xy in ([60.0, 40.0], [160.0, 60.0], [250.0, 80.0]):
        click(app, cal.scene.planes["frame"], xy)
    cal.finish_line()
    app.set_mode("Seed")
    seed = app.views["Seed"]
    seed.panel.auto_fit.value = False
    click(app, seed.scene.planes["frame"], (100.0, 80.0))
    click(app, seed.scene.planes["base"], (300.0, 250.0))
    seed.undo()
    app.set_mode("Evaluate")
    ev = app.views["Evaluate"]
    click(app, ev.scene.planes["frame"], (50.0, 60.0))
    ev.set_frame(1)
    app.set_mode("Sequence")
    app.views["Sequence"].set_frame(1)
    app.worker.wait_idle()


def test_undo_restores_seeds_and_edits():
    from app.gui.controlpoints import Edits

    st = AppState()
    st.push_undo()
    st.seed_frame, st.seed_base = (1.0, 2.0), (3.0, 4.0)
    st.push_undo()
    st.cp_edits = Edits(enabled={3: False})
    assert st.pop_undo() and st.cp_edits.empty and st.seed == (1.0, 2.0, 3.0, 4.0)
    assert st.pop_undo() and st.seed is None
    assert not st.pop_undo()


def test_upload_does_not_open_an_unchecked_path(tmp_path, small_seq, make_app):
    app = make_app(tmp_path / "proj", small_seq)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "f.png").write_bytes((small_seq / "base.png").read_bytes())
    app.inputs_panel.frames_text.value = str(outside / "*.png")

    class Upload:
        name = "base.png"
        content = (small_seq / "base.png").read_bytes()

    app.handle_upload("base", Upload(), None)
    app.worker.wait_idle()
    assert app.inputs.frames_path == str(small_seq / "frames")  # one upload opens nothing
    app.open_paths_from_gui(None)  # ... and the other box's path is checked when opening
    app.worker.wait_idle()
    assert "Path refused" in app.errors[-1] and "outside the allowed folders" in app.errors[-1]
    assert app.inputs.frames_path == str(small_seq / "frames")


def test_serve_allows_only_named_folders(tmp_path, small_seq, monkeypatch):
    from app.gui.launch import serve

    monkeypatch.chdir(tmp_path)
    app = serve(
        frames=str(small_seq / "frames"),
        base=str(small_seq / "base.png"),
        project_dir=str(tmp_path / "proj"),
        port=0,
        block=False,
    )
    try:
        roots = app.allowed_roots()
        assert Path.cwd().resolve() not in roots and small_seq.resolve() in roots
        assert app.server.origin_policy is not None  # handshakes are checked
        app.inputs_panel.frames_text.value = str(tmp_path / "x.png")
        (tmp_path / "x.png").write_bytes(b"x")
        app.open_paths_from_gui(None)
        assert "outside the allowed folders" in app.errors[-1]
    finally:
        app.stop()


def test_transform_choice_reaches_the_run(tmp_path, small_seq, make_app):
    """Projective instead of polyprojective, local field off: the fit and the run use them."""
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Seed")
    seed = app.views["Seed"]
    seed.panel.transform.value = "projective"
    seed.panel.local.value = False
    assert app.state.degree == 1 and not app.state.run_local
    seed_at_truth(app, truth)
    assert app.state.reference.fine.base_from_corrected.degree == 1, app.errors
    assert "(projective)" in seed.panel.cps.summary.content
    app.set_mode("Sequence")
    assert app.views["Sequence"].run()
    app.jobs.join(300)
    app.worker.wait_idle()
    r = app.state.result
    assert all(r.model(k).degree == 1 for k in range(r.n_frames)), app.errors
    assert all(r.field(k) is None for k in range(r.n_frames))
    assert "projective, local field off" in app.views["Sequence"].panel.run_md.content


def test_reference_fit_and_edits_survive_a_restart(fitted, make_app, small_seq, tmp_path):
    app, truth, bxy = fitted
    seed = app.views["Seed"]
    seed.disable_worst()
    app.worker.wait_idle()
    rms, n_enabled = seed.table.rms, seed.table.n_enabled
    app.stop()
    app2 = make_app(tmp_path / "proj", small_seq)
    app2.worker.wait_idle()
    ref = app2.state.current_reference()
    assert ref is not None and ref.fine, app2.errors
    t = app2.views["Seed"].table
    assert t.n_enabled == n_enabled and t.rms == pytest.approx(rms, rel=1e-6)
    assert app2.state.steps()["reference registered"] and app2.state.steps()["seeded"]


def test_import_points_and_lines_files(tmp_path, small_seq, make_app):
    """POINTS.csv and LINES.json made elsewhere (the CLI's formats) are imported into the
    Evaluate and Calibrate views; a file for other frames is refused in one line, nothing
    changed."""
    app = make_app(tmp_path / "proj", small_seq)
    ev, cal = app.views["Evaluate"], app.views["Calibrate"]
    text = "point,frame,x,y\nNW,0,100.5,80.25\nNW,2,103,82\nSE,1,500,400\n"
    assert ev.import_points("mine.csv", text.encode())
    assert app.state.points == {
        "NW": {0: (100.5, 80.25), 2: (103.0, 82.0)},
        "SE": {1: (500.0, 400.0)},
    }
    assert not app.state.pending
    assert "NW,2,103.000,82.000" in app.project.points_path.read_text()
    bad = "point,frame,x,y\nNW,9,1,1\n"
    assert not ev.import_points("bad.csv", bad.encode())
    assert "frame 9 is not in the result" in app.notices[-1][1]
    assert set(app.state.points) == {"NW", "SE"}
    lines = {"version": 1, "image_size": [640, 480], "lines": [[[10, 10], [200, 12], [400, 15]]]}
    assert cal.import_lines("LINES.json", json.dumps(lines).encode())
    assert app.state.lines == [[(10.0, 10.0), (200.0, 12.0), (400.0, 15.0)]]
    assert json.loads(app.project.lines_path.read_text())["lines"] == lines["lines"]
    other = dict(lines, image_size=[1280, 960])
    assert not cal.import_lines("big.json", json.dumps(other).encode())
    assert "drawn on 1280x960 frames; these are 640x480" in app.notices[-1][1]
    assert len(app.state.lines) == 1


@pytest.fixture(scope="module")
def traffic_seq(tmp_path_factory) -> Path:
    """12 frames 640x480 (2.4 s at 5 frames/s) with the simulator's traffic."""
    from registration.synth import SimConfig, simulate

    out = tmp_path_factory.mktemp("traffic_seq")
    simulate(out, SimConfig(frame_size=(640, 480), n_frames=12, video=False, seed=2))
    return out


def test_traffic_view_finds_tracks_on_the_map(tmp_path, traffic_seq, make_app):
    """Find vehicles on the registered sequence: tracks coloured by speed over the map, the
    frame's vehicles where the simulator drove them, a click selects a track and charts its
    speed, the files download; the checklist counts it."""
    from registration.evaluation.traffic import truth_metric_frame
    from registration.synth import load_truth

    truth = load_truth(traffic_seq)
    app = make_app(tmp_path / "proj", traffic_seq)
    app.views["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Seed")
    seed_at_truth(app, truth)
    app.set_mode("Sequence")
    assert app.views["Sequence"].run()
    app.jobs.join(600)
    app.worker.wait_idle()
    assert app.state.result is not None, app.errors
    exporter = app.views["Sequence"].exporter
    exporter.refresh()
    assert exporter.panel.formats["traffic"].disabled  # no traffic run yet
    app.set_mode("Traffic")
    tv = app.views["Traffic"]
    # A plain base map and image frames: metres and times must be given, and the view says so.
    assert not tv.find() and "ground sampling distance" in app.notices[-1][1]
    tv.panel.gsd.value = truth_metric_frame(truth).gsd_m
    assert not tv.find() and "give the frame rate" in app.notices[-1][1]
    tv.panel.fps.value = truth.config["fps"]
    assert app.state.traffic_fps == truth.config["fps"]
    assert tv.find()
    app.jobs.join(600)
    app.worker.wait_idle()
    run = app.state.traffic
    assert run is not None and len(run.tracks) >= 3, app.notices[-3:]
    assert app.state.steps()["traffic found"] and "tracks**" in tv.panel.summary_md.content
    assert tv.scene.planes["base"].overlay("tracks") is not None
    # The vehicles of a frame lie where the simulator drove vehicles (base px).
    v = truth.vehicles()
    k = 6
    ids, xy, speed, boxes = tv.vehicles_at(k)
    at_k = v["frame"] == k
    true_xy = np.c_[v["x_base"][at_k], v["y_base"][at_k]]
    gaps = [np.min(np.hypot(*(true_xy - p).T)) for p in xy]
    px_per_m = 1.0 / truth_metric_frame(truth).gsd_m
    assert len(ids) >= 2 and np.median(gaps) < 2.0 * px_per_m, gaps
    # Each vehicle's box: around its centre, its track's width and length, its long side along
    # the direction the simulator drove the nearest vehicle.
    assert np.allclose(boxes.mean(axis=1), xy, atol=1e-6)
    long_side = boxes[:, 0] - boxes[:, 3]
    nearest = [int(np.argmin(np.hypot(*(true_xy - p).T))) for p in xy]
    true_dir = np.c_[v["ux"][at_k], v["uy"][at_k]][nearest]
    cos = np.abs(np.sum(long_side * true_dir, axis=1)) / np.hypot(*long_side.T)
    assert np.median(cos) > 0.95, cos
    tv.set_frame(k)
    app.worker.wait_idle()
    plane = tv.scene.planes["base"]
    assert plane.overlay("vehicles") is not None
    assert plane.overlay("boxes") is not None
    # Under the boxes, frame k registered to the map (its local stage): drawn over its
    # footprint, which holds the frame's border as the result maps it.
    assert plane.overlay("registered") is not None
    x0, y0, x1, y1 = plane._sized["registered"][1]
    from registration.coords import frame_outline

    border = app.state.result.frame_to_base(k, frame_outline(*app.state.result.frame_size))
    assert np.all(border.min(axis=0) >= (x0, y0)) and np.all(border.max(axis=0) <= (x1, y1))
    assert (x1 - x0) < 1.5 * np.ptp(border[:, 0]) + 50
    # Play moves on frame by frame (5 frames/s) while the view is shown, the frames warped
    # from the smaller playback preview; when it stops, the frame is drawn again at full size.
    from app.gui.views.base import PLAY_SIDE_FRACTION

    tv.panel.play.value = True
    time.sleep(0.7)
    tv.panel.play.value = False
    time.sleep(0.1)
    app.worker.wait_idle()
    shown = app.state.traffic_frame
    assert shown != k
    assert tv.frames.has_warp(shown, "local", int(PLAY_SIDE_FRACTION * app.display_max))
    assert tv.frames.has_warp(shown, "local", 2 * app.display_max)
    # The frame can be hidden: the boxes over the map alone.
    tv.panel.show_frame.value = False
    app.worker.wait_idle()
    assert plane.overlay("registered") is None and plane.overlay("boxes") is not None
    tv.panel.show_frame.value = True
    tv.set_frame(k)
    app.worker.wait_idle()
    assert plane.overlay("registered") is not None
    # A click on a track selects it and charts its speed.
    tv.on_click("base", tuple(xy[0]), None)
    app.worker.wait_idle()
    assert tv.selected == ids[0] and tv.panel.plot.visible
    frames, speeds = tv.panel.plot.data
    assert k in frames.tolist() and np.all(np.isfinite(speeds))
    assert f"Track **{ids[0]}**" in tv.panel.track_md.content
    sent = []
    app.send_download = lambda client, name, data: sent.append((name, data))
    assert tv.download("tracks.csv")
    assert sent and sent[0][0] == "tracks.csv" and sent[0][1].startswith(b"recordingId,trackId")
    # A road section drawn across the selected track's path (two clicks) counts it, in its
    # direction of travel; the counts download; the section is saved with the project.
    tr, b = next(
        (t, b) for t, b in zip(run.tracks, run.base_xy, strict=True) if t.track_id == ids[0]
    )
    i = int(np.flatnonzero(tr.frames == k)[0])
    i = min(i, len(b) - 2)
    mid, step = (b[i] + b[i + 1]) / 2, b[i + 1] - b[i]
    across = np.array([-step[1], step[0]]) / np.hypot(*step) * 5.0 * px_per_m
    tv.start_section()
    tv.on_click("base", tuple(mid - across), None)
    tv.on_click("base", tuple(mid + across), None)
    app.worker.wait_idle()
    assert len(app.state.traffic_sections) == 1
    assert tv.scene.planes["base"].overlay("sections") is not None
    crossings = (tv.out_dir / "crossings.csv").read_text().splitlines()
    assert any(line.split(",")[2] == str(ids[0]) for line in crossings[1:]), crossings
    heading = np.degrees(np.arctan2(*tr.velocity[i])) % 360  # clockwise from north
    compass = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")[int(round(heading / 45)) % 8]
    assert f"| S1 | {compass} |" in tv.panel.counts_md.content, tv.panel.counts_md.content
    assert tv.download("counts.csv") and sent[-1][1].startswith(b"section,direction,heading")
    assert json.loads((app.project.folder / "project.json").read_text())["traffic_sections"]
    # The Sequence view's Export panel exports the traffic files too: copies of the run's.
    exporter.refresh()
    assert not exporter.panel.formats["traffic"].disabled
    assert exporter.request(formats=["traffic"])
    app.jobs.join(120)
    app.worker.wait_idle()
    expected = {p.name for p in exporter.traffic_files()}
    assert {"tracks.csv", "trajectories.geojson", "velocity_field.tif", "counts.csv"} <= expected
    copied = app.project.folder / "exports" / "traffic"
    assert {p.name for p in copied.iterdir()} == expected
    assert all((copied / n).read_bytes() == (tv.out_dir / n).read_bytes() for n in expected)
    assert any(label.startswith("traffic: ") for label in exporter.format_of_label)
    # Exporting again asks before replacing them.
    assert not exporter.request(formats=["traffic"])
    assert exporter.answer("overwrite")
    app.jobs.join(120)
    app.worker.wait_idle()
    tv.remove_last_section()
    app.worker.wait_idle()
    assert not app.state.traffic_sections and tv.panel.counts_md.content == ""
    assert not (tv.out_dir / "counts.csv").exists()  # nothing stale to download
