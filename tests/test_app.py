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

from app import scene2d  # noqa: E402
from app.project import Project, write_atomic  # noqa: E402
from app.security import make_server  # noqa: E402
from app.server import App  # noqa: E402
from app.state import AppState  # noqa: E402
from app.worker import LatestWorker  # noqa: E402
from registration import viz  # noqa: E402
from registration.distortion import HarrisModel  # noqa: E402

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


def test_calibrate_gamma_lines_and_restore(tmp_path, small_seq, make_app):
    from registration.calibration import load_lines

    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    cal = app.tabs["Calibrate"]
    assert app.shown["Calibrate"] == (0, 0.0, 640, 480)
    cal.gamma_slider.value = 0.5
    app.worker.wait_idle()
    assert app.state.gamma == 0.5 and cal.gamma_number.value == 0.5
    assert app.shown["Calibrate"][:2] == (0, 0.5)
    cal.gamma_number.value = 0.6123
    app.worker.wait_idle()
    assert app.state.gamma == pytest.approx(0.6123) and cal.gamma_slider.value == pytest.approx(
        0.61
    )
    assert json.loads((proj / "project.json").read_text())["gamma"] == pytest.approx(0.6123)
    # An invalid γ (beyond the Harris validity limit) is refused and the old one kept.
    cal.gamma_number.value = 3.0
    app.worker.wait_idle()
    assert app.state.gamma == pytest.approx(0.6123) and "Invalid γ" in app.errors[-1]
    # Three clicks on the corrected image make a line stored in RAW pixels.
    clicked = np.array([[60.0, 40.0], [160.0, 60.0], [250.0, 80.0]])
    for xy in clicked:
        assert click(app, cal.image_planes["frame"], xy)[0] == "frame"
    cal.finish_line()
    app.worker.wait_idle()
    model = HarrisModel(0.6123, 640, 480)
    raw = np.array(app.state.lines[0])
    assert np.allclose(model.corrected_from_raw(raw), clicked, atol=1e-6)
    saved = load_lines(proj / "LINES.json")
    assert saved.image_size == (640, 480) and np.allclose(saved.lines[0], raw)
    assert "Overall" in cal.lines_md.content  # straightness shown
    # A click outside the image does nothing.
    o, d = cal.image_planes["frame"].geom.ray_towards_pixel((-20.0, 10.0), CAMERA)
    assert app.handle_click(o, d) is None
    app.stop()
    # Restarting on the same project restores γ and lines.
    app2 = make_app(proj, small_seq)
    assert app2.state.gamma == pytest.approx(0.6123)
    assert np.allclose(np.array(app2.state.lines[0]), raw)
    assert app2.tabs["Calibrate"].gamma_number.value == pytest.approx(0.6123)


def test_seed_clicks_are_raw_pixels_and_replace(tmp_path, small_seq, make_app):
    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    app.tabs["Calibrate"].gamma_number.value = 0.7
    app.set_mode("Seed")
    app.worker.wait_idle()
    seed = app.tabs["Seed"]
    assert click(app, seed.image_planes["frame"], (100.25, 80.75))[0] == "frame"
    assert click(app, seed.image_planes["base"], (300.5, 250.0))[0] == "base"
    assert click(app, seed.image_planes["base"], (310.0, 260.0))[0] == "base"  # replaces
    fx, fy, bx, by = app.state.seed
    corrected = HarrisModel(0.7, 640, 480).corrected_from_raw([(fx, fy)])[0]
    assert np.allclose(corrected, (100.25, 80.75), atol=1e-6)
    assert (bx, by) == pytest.approx((310.0, 260.0), abs=1e-6)
    saved = json.loads((proj / "project.json").read_text())
    assert saved["seed_base"] == pytest.approx([310.0, 260.0]) and saved["mode"] == "Seed"
    seed.clear_seed()
    assert app.state.seed is None


def test_bad_path_and_oversized_upload_notify(tmp_path, small_seq, make_app):
    app = make_app(tmp_path / "proj", small_seq, max_upload_mb=0.001)
    app.frames_text.value = "/etc"
    app.base_text.value = str(small_seq / "base.png")
    app.open_paths_from_gui(None)
    assert "Path refused" in app.errors[-1] and "outside the allowed folders" in app.errors[-1]

    class Upload:
        name = "big.mp4"
        content = b"\0" * 5000

    app.handle_upload("frames", Upload(), None)
    assert "Upload refused" in app.errors[-1] and "limit" in app.errors[-1]
    assert app.inputs.frames_path == str(small_seq / "frames")  # inputs unchanged


def test_upload_base_then_open(tmp_path, small_seq, make_app):
    app = make_app(tmp_path / "proj", small_seq)

    class Upload:
        name = "my base.png"
        content = (small_seq / "base.png").read_bytes()

    app.handle_upload("base", Upload(), None)
    app.worker.wait_idle()
    assert Path(app.inputs.base_path).name == "base-my_base.png"
    assert Path(app.inputs.base_path).parent == app.project.uploads_dir


def test_coarse_fine_and_sequence_in_process(tmp_path, small_seq, make_app):
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    app.tabs["Calibrate"].gamma_number.value = truth.gamma
    app.set_mode("Seed")
    seed = app.tabs["Seed"]
    fxy = np.array([320.0, 240.0])
    bxy = truth.frame_to_base(0, fxy[None])[0]
    corrected = HarrisModel(truth.gamma, 640, 480).corrected_from_raw(fxy[None])[0]
    click(app, seed.image_planes["frame"], corrected)
    click(app, seed.image_planes["base"], bxy)
    assert seed.run_coarse()
    app.jobs.join(120)
    app.worker.wait_idle()
    coarse = app.state.coarse
    assert coarse is not None and coarse.success, app.errors
    assert "inliers" in seed.coarse_md.content and seed._matches is not None
    assert seed.run_fine()
    app.jobs.join(120)
    app.worker.wait_idle()
    assert app.state.fine is not None and app.state.fine.success, app.errors
    assert seed.image_planes["base"].has("residuals")
    seed.show_template_matches.value = True
    app.worker.wait_idle()
    assert seed._template_lines is not None
    seed.mid_opacity.value = 0.7
    app.worker.wait_idle()
    assert seed.image_planes["base"].has("mid")
    app.set_mode("Sequence")
    seq = app.tabs["Sequence"]
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    assert seq.result is not None and all(r["status"] == "ok" for r in seq.result.records), (
        app.errors
    )
    seq.scrub.value = 2
    app.worker.wait_idle()
    assert app.state.seq_frame == 2 and app.shown["Sequence"][0] == 2 and app.shown["Sequence"][3]
    seq.show_field.value = True
    seq.overlay.value = "checkerboard"
    app.worker.wait_idle()
    assert app.shown["Sequence"][2] == "checkerboard"
    # A click on the error plot at frame 1's column jumps there.
    plot = seq.image_planes["plot"]
    x0, x1 = seq._plot_x
    u = x0 + (x1 - x0) * 1 / 3
    click(app, plot, ((u / 960) * plot.geom.width - 0.5, plot.geom.height / 2))
    app.worker.wait_idle()
    assert app.state.seq_frame == 1
    seq.jump_to_worst()
    vals = seq.error_values()
    assert app.state.seq_frame == int(np.nanargmax(vals))
    # Evaluate: points marked at their true raw positions; the proposal for the next frame comes
    # from the result; Table 2 from the evaluation module.
    app.set_mode("Evaluate")
    ev = app.tabs["Evaluate"]
    b = np.array([[bxy[0], bxy[1]]])
    for k in (0, 1):
        ev.set_frame(k)
        click(app, ev.image_planes["frame"], truth.base_to_frame(k, b)[0])
    assert ev.propose_next()
    app.worker.wait_idle()
    proposed = np.array(app.state.points["NW"][2])
    assert app.state.eval_frame == 2 and ("NW", 2) in ev.proposed
    assert np.hypot(*(proposed - truth.base_to_frame(2, b)[0])) < 3.0
    assert ev.compute_table()
    app.jobs.join(60)
    assert "Post-Global" in ev.table_md.content and "Post-Local" in ev.table_md.content, app.errors
    assert (proj / "TABLE2.csv").exists()
    # The result survives a restart of the app.
    app.stop()
    app2 = make_app(proj, small_seq)
    assert app2.tabs["Sequence"].result is not None
    assert app2.state.seed is not None and app2.state.gamma == pytest.approx(truth.gamma)
    # ... and so do the coarse and fine results of the Seed view (saved for this γ and seed).
    assert app2.state.coarse is not None and app2.state.coarse.n_inliers == coarse.n_inliers
    assert app2.state.fine is not None and app2.state.fine.success
    assert np.allclose(
        app2.state.fine.base_from_corrected.apply(app2.state.fine.src[:5]),
        app.state.fine.base_from_corrected.apply(app.state.fine.src[:5]),
    )
    assert "inliers" in app2.tabs["Seed"].coarse_md.content


def test_evaluate_marks_points(tmp_path, small_seq, make_app):
    proj = tmp_path / "proj"
    app = make_app(proj, small_seq)
    app.set_mode("Evaluate")
    ev = app.tabs["Evaluate"]
    app.worker.wait_idle()
    click(app, ev.image_planes["frame"], (50.0, 60.0))
    ev.frame_slider.value = 2
    click(app, ev.image_planes["frame"], (52.5, 61.0))
    ev.new_point()
    click(app, ev.image_planes["frame"], (200.0, 100.0))
    pts = app.state.points
    assert sorted(pts) == ["NE", "NW"] and sorted(pts["NW"]) == [0, 2] and list(pts["NE"]) == [2]
    assert pts["NW"][0] == pytest.approx((50.0, 60.0), abs=1e-6)
    assert pts["NW"][2] == pytest.approx((52.5, 61.0), abs=1e-6)
    assert pts["NE"][2] == pytest.approx((200.0, 100.0), abs=1e-6)
    assert [r[:2] for r in ev.points_rows()] == [(0, "NW"), (2, "NW"), (2, "NE")]
    saved = json.loads((proj / "project.json").read_text())
    assert saved["points"]["NW"]["2"] == pytest.approx([52.5, 61.0], abs=1e-6)
    # POINTS.csv is written as marks change and reads back with the evaluation module.
    from registration.evaluation import read_points_csv

    marks = read_points_csv(proj / "POINTS.csv", 4, (640, 480), min_frames=1)
    assert marks.marks["NW"][2] == pytest.approx((52.5, 61.0), abs=1e-3)
    assert ev.export_csv()  # saved, checked with the evaluation reader, sent to the browser
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
    cal = app.tabs["Calibrate"]
    plane = cal.image_planes["frame"]
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
    cal.estimate(auto=False)
    app.jobs.join(120)
    app.worker.wait_idle()
    assert app.state.gamma == pytest.approx(truth.gamma, abs=0.05), app.errors
    assert cal.plot is not None and "from lines" in cal.estimate_md.content
    assert json.loads(app.project.session_path.read_text())["gamma"] == pytest.approx(
        app.state.gamma
    )
    cal.set_gamma(0.0)
    cal.estimate(auto=True)
    app.jobs.join(180)
    assert app.state.gamma == pytest.approx(truth.gamma, abs=0.1), (
        app.errors,
        cal.estimate_md.content,
    )


def test_sequence_cancel_resume_play_and_flicker(tmp_path, small_seq, make_app):
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    app = make_app(tmp_path / "proj", small_seq)
    app.tabs["Calibrate"].set_gamma(truth.gamma)
    app.set_mode("Sequence")
    seq = app.tabs["Sequence"]
    records = app.project.result_dir / "frames"
    assert seq.run()
    # Cancel as soon as the first frame is written: the run stops after the frame in progress.
    t0 = time.monotonic()
    while not (records.is_dir() and any(records.glob("*.json"))) and time.monotonic() - t0 < 120:
        time.sleep(0.01)
    app.jobs.request_cancel()
    app.jobs.join(120)
    app.worker.wait_idle()
    statuses = [r["status"] for r in seq.result.records]
    assert "pending" in statuses and statuses.count("ok") >= 1, statuses
    assert "Registration cancelled" in [n[0] for n in app.notices]
    done = {p.name: p.stat().st_mtime_ns for p in records.glob("*.json")}
    # Running again resumes: finished frames are not redone.
    assert seq.run()
    app.jobs.join(300)
    app.worker.wait_idle()
    assert all(r["status"] == "ok" for r in seq.result.records), app.errors
    assert all((records / n).stat().st_mtime_ns == m for n, m in done.items())
    # Play advances the scrubber; pausing stops it.
    seq.set_frame(0)
    seq.play.value = True
    t0 = time.monotonic()
    while app.state.seq_frame == 0 and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    seq.play.value = False
    assert app.state.seq_frame != 0
    time.sleep(0.5)
    app.worker.wait_idle()
    k = app.state.seq_frame
    time.sleep(1.0)
    assert app.state.seq_frame == k
    # Flicker toggles the registered overlay on and off.
    seq.overlay.value = "flicker"
    app.worker.wait_idle()
    handle = seq.image_planes["base"]._overlays["registered"]
    seen = set()
    t0 = time.monotonic()
    while len(seen) < 2 and time.monotonic() - t0 < 5:
        seen.add(bool(handle.visible))
        time.sleep(0.05)
    assert seen == {True, False}


def test_upload_does_not_open_an_unchecked_path(tmp_path, small_seq, make_app):
    app = make_app(tmp_path / "proj", small_seq)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "f.png").write_bytes((small_seq / "base.png").read_bytes())
    app.frames_text.value = str(outside / "*.png")

    class Upload:
        name = "base.png"
        content = (small_seq / "base.png").read_bytes()

    app.handle_upload("base", Upload(), None)
    app.worker.wait_idle()
    assert "Path refused" in app.errors[-1] and "outside the allowed folders" in app.errors[-1]
    assert app.inputs.frames_path == str(small_seq / "frames")


def test_serve_allows_only_named_folders(tmp_path, small_seq, monkeypatch):
    from app.server import serve

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
        app.frames_text.value = str(tmp_path / "x.png")
        (tmp_path / "x.png").write_bytes(b"x")
        app.open_paths_from_gui(None)
        assert "outside the allowed folders" in app.errors[-1]
    finally:
        app.stop()
