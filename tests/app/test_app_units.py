"""Unit tests of the app's pure parts: control-point tables and their re-fit, the QGIS export,
screen-space helpers, the static assets and the event channel."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.gui import assets, controlpoints, scene2d
from app.gui.controlpoints import Edits
from registration.geometry import PolyProjective, Projective
from registration.lens import HarrisModel


@pytest.fixture
def known():
    """Corrected frame points, their exact images under a known projective, and outliers at
    named indices (3 and 17) moved by 40 px."""
    rng = np.random.default_rng(7)
    proj = Projective.from_matrix(
        np.array([[1.1, 0.05, 30.0], [-0.04, 1.05, 12.0], [1e-5, 2e-5, 1.0]])
    )
    model = PolyProjective.from_projective(proj, 2)
    src = rng.uniform([20, 20], [620, 460], (60, 2))
    dst = model.apply(src)
    dst[[3, 17]] += 40.0
    kept = np.ones(60, bool)
    kept[[3, 17]] = False
    return src, dst, kept, model


def test_table_residuals_and_order(known):
    src, dst, kept, model = known
    harris = HarrisModel(0.3, 640, 480)
    t = controlpoints.table_from_points(src, dst, kept, None, "reference", harris, model)
    assert t.n_enabled == 58 and t.rms == pytest.approx(0.0, abs=1e-6)
    # The two outliers have 40*sqrt(2) px residuals, first when sorted by residual.
    assert set(t.ids[t.order("residual")[:2]]) == {3, 17}
    assert t.residual[3] == pytest.approx(40 * np.sqrt(2), rel=1e-6)
    assert np.allclose(t.residual_xy[17], (-40.0, -40.0))
    # Frame points are shown in raw pixels: back through the Harris model they are the source.
    assert np.allclose(harris.corrected_from_raw(t.frame_xy), src, atol=1e-6)
    assert t.source[0] == "template" and list(t.order("id")) == list(range(60))


def test_refit_follows_the_enabled_points(known):
    src, dst, kept, model = known
    harris = HarrisModel(0.0, 640, 480)
    start = PolyProjective.from_projective(Projective.from_matrix(np.eye(3)), 2)
    # Enabling an outlier pulls the fit; disabling it again restores the exact model.
    t = controlpoints.table_from_points(
        src, dst, kept, None, "reference", harris, model, Edits(enabled={3: True})
    )
    t1, m1 = controlpoints.refit(t, start)
    assert m1 is not None and t1.rms > 1.0
    t2, m2 = controlpoints.refit(
        controlpoints.table_from_points(src, dst, kept, None, "reference", harris, model), start
    )
    assert t2.rms < 1e-3
    # Disabling the worst enabled point never raises the RMS (least squares on a subset).
    w = t1.worst_enabled()
    assert w == 3
    t3, _ = controlpoints.refit(
        controlpoints.table_from_points(
            src, dst, kept, None, "reference", harris, model, Edits(enabled={3: True, w: False})
        ),
        m1,
    )
    assert t3.rms <= t1.rms
    # Too few points for the degree: no model, and the reason says why.
    few = Edits(enabled={i: i < 5 for i in range(60)})
    t4, m4 = controlpoints.refit(
        controlpoints.table_from_points(src, dst, kept, None, "reference", harris, model, few),
        start,
    )
    assert m4 is None and "needs at least" in t4.reason and not np.isfinite(t4.rms)


def test_manual_and_deleted_points(known):
    src, dst, kept, model = known
    harris = HarrisModel(0.5, 640, 480)
    raw = harris.raw_from_corrected(np.array([[300.0, 200.0]]))[0]
    b = model.apply(np.array([[300.0, 200.0]]))[0]
    edits = Edits(deleted={0, 1}, manual=[(*raw, *b)])
    t = controlpoints.table_from_points(src, dst, kept, None, "reference", harris, model, edits)
    assert len(t.ids) == 59 and 0 not in t.ids and t.ids[-1] == 60
    assert t.source[-1] == "manual" and t.residual[-1] == pytest.approx(0.0, abs=1e-6)
    back = Edits.from_json(json.loads(json.dumps(edits.to_json())))
    assert back.deleted == {0, 1} and np.allclose(back.manual, edits.manual)
    assert Edits.from_json("garbage").empty


def test_qgis_points_plain_and_georeferenced(known, tmp_path):
    from registration.gis import GeoReference, parse_crs, read_points_file

    src, dst, kept, model = known
    harris = HarrisModel(0.0, 640, 480)
    t = controlpoints.table_from_points(
        src[:3], dst[:3], kept[:3], None, "reference", harris, model
    )
    plain = controlpoints.write_qgis_points(t, tmp_path / "plain.points")
    lines = plain.read_text().splitlines()
    assert lines[0] == "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"
    # Pixel centres at integers -> QGIS pixel corners, rows negative (source and plain map).
    rows = np.array([[float(v) for v in line.split(",")[:5]] for line in lines[1:]])
    assert np.allclose(rows[:, 2], src[:3, 0] + 0.5) and np.allclose(
        rows[:, 3], -(src[:3, 1] + 0.5)
    )
    assert np.allclose(rows[:, 0], dst[:3, 0] + 0.5) and np.allclose(
        rows[:, 1], -(dst[:3, 1] + 0.5)
    )
    assert list(rows[:, 4]) == [1, 1, 1]
    # A georeferenced base: map coordinates in its CRS, residuals in map units.
    georef = GeoReference((0.25, 0.0, 500000.0, 0.0, -0.25, 4000000.0), "EPSG:32612")
    t2 = controlpoints.with_residuals(t, model)
    t2.residual_xy[:] = (2.0, -4.0)  # known residuals: 0.5 m east, 1 m north
    geo = read_points_file(controlpoints.write_qgis_points(t2, tmp_path / "geo.points", georef))
    assert parse_crs(geo["crs"]).to_epsg() == 32612
    assert np.allclose(geo["map"], georef.map_from_base(dst[:3]), atol=1e-9)
    assert np.allclose(geo["source"], t.frame_xy, atol=1e-9)
    text = (tmp_path / "geo.points").read_text().splitlines()
    dx, dy = (float(v) for v in text[2].split(",")[5:7])
    assert (dx, dy) == pytest.approx((0.5, 1.0))
    # Read back (the app's import): raw frame px and base px again, plain and georeferenced.
    for path, g in ((plain, None), (tmp_path / "geo.points", georef)):
        rows, enabled = controlpoints.read_qgis_points(path, (640, 480), (2000, 2000), g)
        assert np.allclose(rows, np.c_[src[:3], dst[:3]], atol=1e-6) and enabled.all()
    other = GeoReference(georef.transform, "EPSG:32613")
    with pytest.raises(ValueError, match=r"geo.points: its map coordinates are in WGS 84 / UTM "
                       r"zone 12N, the base map's in WGS 84 / UTM zone 13N"):  # fmt: skip
        controlpoints.read_qgis_points(tmp_path / "geo.points", (640, 480), (2000, 2000), other)
    with pytest.raises(ValueError, match=r"geo.points: its map coordinates are in WGS 84 / UTM "
                       r"zone 12N, and the base map has no georeference"):  # fmt: skip
        controlpoints.read_qgis_points(tmp_path / "geo.points", (640, 480), (2000, 2000), None)


def test_clip_segments_known_cases():
    a = np.array([[-10.0, 5.0], [2.0, 2.0], [-5.0, -5.0], [np.nan, 0.0]])
    b = np.array([[20.0, 5.0], [4.0, 3.0], [-1.0, -1.0], [3.0, 3.0]])
    s, e, keep = scene2d.clip_segments(a, b, 10, 8)
    assert list(keep) == [True, True, False, False]
    assert np.allclose(s[0], (-0.5, 5.0)) and np.allclose(e[0], (9.5, 5.0))
    assert np.allclose(s[1], (2, 2)) and np.allclose(e[1], (4, 3))


def test_auto_vector_scale_and_zoom_helpers():
    assert scene2d.auto_vector_scale([], 1000) == 1.0
    k = scene2d.auto_vector_scale(np.full(100, 0.5), 1000)  # 3 % of 1000 px / 0.5 px = 60
    assert k in (50.0, 100.0) and 0.5 * k == pytest.approx(30, rel=0.7)
    # A camera 2 units up with a 60° field and 600 px: 2*2*tan(30°)/600 world units per px.
    assert scene2d.world_per_screen_px(-2.0, np.deg2rad(60), 600) == pytest.approx(
        4 * np.tan(np.deg2rad(30)) / 600
    )
    g = scene2d.PlaneGeometry(100, 80)
    assert np.allclose(
        scene2d.pixel_under_pointer(g, (0, 0, -1.0), g.world_from_pixel([30.0, 20.0], -0.01)),
        (30.0, 20.0),
        atol=0.5,
    )


class _HiddenTextGui:
    """Enough of viser's GUI for an EventChannel: a text widget whose updates go nowhere."""

    def add_text(self, *a, **k):
        class Widget:
            def on_update(self, cb):
                pass

        return Widget()


def test_static_assets_and_event_channel():
    for name in ("camera.js", "events.js", "app.css"):
        assert assets.read_asset(name).strip()
    assert "__CHANNEL__" in assets.read_asset("events.js")
    js = assets.css_loader_js("a { b: 'c' }")
    assert "aerialreg-css" in js and json.dumps("a { b: 'c' }") in js
    with pytest.raises(FileNotFoundError, match="missing"):
        assets.read_asset("nope.js")

    ch = assets.EventChannel(_HiddenTextGui())
    got = []
    ch.on("cp-select:seed", lambda v, c: got.append(v))
    assert ch.dispatch(json.dumps({"kind": "cp-select:seed", "value": 12, "n": 1}))
    assert not ch.dispatch(json.dumps({"kind": "nope", "value": 1}))
    assert not ch.dispatch("not json") and not ch.dispatch(json.dumps([1, 2]))
    assert got == [12]


def test_a_malformed_event_value_is_refused_without_a_traceback(caplog):
    """A page may send any value: the handler's ValueError is one log line, not a traceback."""
    import logging

    ch = assets.EventChannel(_HiddenTextGui())
    ch.on("cp-select:seed", lambda v, c: int(v))
    with caplog.at_level(logging.WARNING):
        assert not ch.dispatch(json.dumps({"kind": "cp-select:seed", "value": "abc"}))
        assert not ch.dispatch(json.dumps({"kind": "cp-select:seed", "value": None}))
    assert len(caplog.records) == 2 and not any(r.exc_info for r in caplog.records)
    assert "event 'cp-select:seed' refused: invalid literal" in caplog.records[0].getMessage()


def test_second_seed_from_typed_heading_round_trips():
    from app.gui import calls

    rng = np.random.default_rng(5)
    size = (640, 480)
    harris = HarrisModel(0.7, *size)
    for heading, scale in [(0.0, 1.0), (95.5, 1.09), (271.25, 0.37), (359.9, 3.2)]:
        seed = (*rng.uniform((20, 20), (620, 460)), *rng.uniform(0, 1000, 2))
        pair = calls.second_seed_from_similarity(seed, heading, scale, 0.7, size)
        c1, c2 = harris.corrected_from_raw(np.array([seed[:2], pair[:2]]))
        assert np.hypot(*(c2 - c1)) == pytest.approx(calls.TYPED_SEED_DISTANCE_PX, abs=1e-6)
        back = calls.heading_from_pairs(seed, pair, 0.7, size)
        assert back.scale == pytest.approx(scale, rel=1e-9)
        assert abs((back.heading_deg - heading + 180) % 360 - 180) < 1e-7
    for heading, scale in [(10.0, 0.0), (10.0, -1.0), (float("nan"), 1.0)]:
        with pytest.raises(ValueError, match="scale positive"):
            calls.second_seed_from_similarity((1.0, 2.0, 3.0, 4.0), heading, scale, 0.7, size)


def test_job_runner_reports_start_before_a_job_that_ends_at_once():
    """A job that finishes before ``start`` returns (an export refused at once) must not have
    its finish overtaken by its start: the app's header would show a job that is not running."""
    from app.gui.worker import JobRunner

    events = []
    runner = JobRunner(
        on_start=lambda job: events.append(("start", job.name)),
        on_finish=lambda job: events.append(("finish", job.name)),
    )
    for name in ("a", "b", "c"):
        assert runner.start(name, lambda job: None)
        assert runner.join(10)
    assert events == [(kind, n) for n in ("a", "b", "c") for kind in ("start", "finish")]


def test_an_upload_with_a_long_name_is_stored_under_a_short_safe_one(tmp_path):
    from app.gui.project import upload_name

    name = upload_name("frames", "flight " + "x" * 240 + ".mp4", b"content")
    assert len(name.encode()) <= 255 and name.endswith(".mp4") and name.startswith("frames-")
    (tmp_path / name).write_bytes(b"content")  # the file system takes it


def test_another_projects_upload_is_shared_not_taken(tmp_path):
    """Opening a file from another project's uploads gives this project its own link to it;
    the other project keeps its file, and pruning either leaves the other's."""
    from app.gui.project import PROJECT_FILE, Project, upload_name

    first, second = Project(tmp_path / "a"), Project(tmp_path / "b")
    for p in (first, second):
        (p.folder / PROJECT_FILE).write_text("{}")
    first.uploads_dir.mkdir()
    source = first.uploads_dir / upload_name("frames", "v.mp4", b"video bytes")
    source.write_bytes(b"video bytes")
    adopted = Path(second.adopt_upload(str(source)))
    assert adopted.parent == second.uploads_dir and adopted.read_bytes() == b"video bytes"
    assert source.read_bytes() == b"video bytes"  # still in the first project
    first.prune_uploads([])
    assert not source.exists() and adopted.read_bytes() == b"video bytes"


def test_residuals_in_map_units_where_the_base_has_a_projected_crs():
    """With a UTM base of 0.5 m pixels the table adds each residual in metres; degrees and
    plain images keep pixels only."""
    from types import SimpleNamespace

    from app.gui.views.cptable.panel import table_html
    from app.gui.views.cptable.table import map_unit
    from registration.gis import GeoReference

    utm = SimpleNamespace(base_georef=GeoReference((0.5, 0, 5e5, 0, -0.5, 4.1e6), "EPSG:32633"))
    wgs = SimpleNamespace(base_georef=GeoReference((1e-5, 0, 73.0, 0, -1e-5, 33.6), "EPSG:4326"))
    assert map_unit(utm) == ("m", 0.5)
    assert map_unit(wgs) is None and map_unit(SimpleNamespace(base_georef=None)) is None
    table = controlpoints.ControlPointTable(
        ids=np.array([0, 1]),
        frame_xy=np.zeros((2, 2)),
        corrected_xy=np.zeros((2, 2)),
        base_xy=np.zeros((2, 2)),
        source=["sift", "manual"],
        enabled=np.array([True, True]),
        kept_by_reqcon=np.array([True, True]),
        model=None,
        residual_xy=np.array([[3.0, 4.0], [0.6, 0.8]]),
    )
    html = table_html(table, [0, 1], None, "seed", map_unit(utm))
    assert "<th>res. (m)</th>" in html and "<td>5.00</td><td>2.500</td>" in html
    assert "<td>1.00</td><td>0.500</td>" in html
    assert "res. (m)" not in table_html(table, [0, 1], None, "seed", None)


def test_play_clock_keeps_its_rate_when_polled_late():
    """Polled every 13 ms (never on a deadline), the clock still gives 5 frames a second: the
    earlier clock ("a period since the tick was seen") gave one every 208 ms, 4.8 a second."""
    from app.gui.views.base import PlayClock

    clock = PlayClock(0.2)
    polls = np.arange(0.0, 10.0, 0.013)
    due = [t for t in polls if clock.due(True, float(t))]
    assert len(due) == 49  # 0.2, 0.4, ... 9.8 s: the first one period after Play
    assert np.abs(np.diff(due) - 0.2).max() < 0.013
    # Not playing: nothing is due, and Play again starts one period later, not at once.
    assert not clock.due(False, 10.5)
    assert not clock.due(True, 11.0)
    assert not clock.due(True, 11.19)
    assert clock.due(True, 11.2)
    # After a stall (a busy machine) it starts afresh from the late tick, without a burst.
    assert clock.due(True, 13.0)
    assert not clock.due(True, 13.1)
    assert clock.due(True, 13.2)
