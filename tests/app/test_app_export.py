"""Exports from the app (Sequence view, ``app/views/export.py``), in process without a browser.

One registration of the 4-frame simulated sequence is shared; each test opens it in a fresh
project, with the plain PNG base or the same base as a GeoTIFF of known transform and CRS.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

viser = pytest.importorskip("viser")

from registration.gis import GeoReference  # noqa: E402
from tests.app.test_app import small_seq  # noqa: E402,F401  (session fixture)

TRANSFORM = (0.5, 0.0, 300000.0, 0.0, -0.5, 3700000.0)  # 0.5 m pixels, UTM 43N
CRS = "EPSG:32643"


@pytest.fixture(scope="module")
def registered_dir(small_seq, tmp_path_factory):  # noqa: F811
    """The small sequence registered with a seed at the truth (plain base)."""
    from app.gui import calls
    from registration.io import frames, images
    from registration.run import pipeline
    from registration.synth import load_truth

    truth = load_truth(small_seq)
    fxy = np.array([[320.0, 240.0]])
    bxy = truth.frame_to_base(0, fxy)[0]
    out = tmp_path_factory.mktemp("registered") / "result"
    pipeline.register_sequence(
        frames.open_frames(small_seq / "frames"),
        images.read_image(small_seq / "base.png"),
        truth.gamma,
        out,
        config=calls.pipeline_config("default", 2, True),
        seed=(*fxy[0], *bxy),
        base_path=small_seq / "base.png",
    )
    return out


@pytest.fixture(scope="module")
def tif_base(small_seq, tmp_path_factory):  # noqa: F811
    """The simulated base map as a GeoTIFF (known transform and CRS)."""
    from registration.gis import write_geotiff
    from registration.io import images

    path = tmp_path_factory.mktemp("tif") / "base.tif"
    write_geotiff(path, images.read_image(small_seq / "base.png"), GeoReference(TRANSFORM, CRS))
    return path


@pytest.fixture
def open_registered(tmp_path, small_seq, registered_dir):  # noqa: F811
    """``open(base)``: an app on the frames and ``base`` whose project holds the registered
    result, Sequence view shown."""
    from app.gui.project import Project
    from app.gui.security import make_server
    from app.gui.server import App

    apps = []

    def open_(base: Path):
        proj = tmp_path / f"proj{len(apps)}"
        shutil.copytree(registered_dir, proj / "result")
        session = {"result_dir": str(proj / "result"), "mode": "Sequence", "gamma": 0.7}
        # The inputs the result was made from (other inputs start afresh).
        session.update(frames_path=str(small_seq / "frames"), base_path=str(base))
        Project(proj).save(session)
        app = App(
            make_server("127.0.0.1", 0, verbose=False),
            Project(proj),
            frames=str(small_seq / "frames"),
            base=str(base),
            allowed_dirs=[tmp_path, small_seq],
        )
        apps.append(app)
        app.start()
        app.worker.wait_idle()
        assert app.state.result is not None and app.state.result.is_ok(3), app.errors
        return app

    yield open_
    for app in apps:
        app.stop()


def capture_downloads(app) -> list[tuple[str, bytes]]:
    sent: list[tuple[str, bytes]] = []
    app.send_download = lambda client, name, data: sent.append((name, data))
    return sent


def run_export(app, formats, **kw) -> bool:
    started = app.views["Sequence"].exporter.request(None, formats=formats, **kw)
    app.jobs.join(300)
    app.worker.wait_idle()
    return started


def test_plain_base_disables_map_formats_asks_before_overwriting_and_downloads(
    open_registered,
    small_seq,  # noqa: F811
):
    app = open_registered(small_seq / "base.png")
    ex = app.views["Sequence"].exporter
    panel = ex.panel
    # Map formats are disabled, and the panel says why in one line.
    disabled = {f for f, box in panel.formats.items() if box.disabled}
    # (.points of a plain base are in its own pixel grid, as the Seed view and the CLI write.)
    # (and the traffic files: the Traffic view has not run)
    assert disabled == {"geotiff", "cog", "mosaic", "geojson", "gpkg", "traffic"}
    assert "has no georeference" in panel.georef_md.content
    assert not panel.btn_export.disabled
    # Video + transforms: written into exports/, progress reported up to its total.
    seen = []
    on_progress = app.jobs._on_progress
    app.jobs._on_progress = lambda job: (seen.append((job.done, job.total)), on_progress(job))
    assert run_export(app, ["mp4", "transforms"])
    out = app.project.folder / "exports"
    assert (out / "registered.mp4").stat().st_size > 1000
    doc = json.loads((out / "transforms.json").read_text())
    assert len(doc["frames"]) == 4
    total = seen[-1][1]
    assert total and seen[-1][0] == total, seen
    assert "Export done" in panel.result_md.content and "| mp4 | 2 |" in panel.result_md.content
    # The written files are offered: one file as it is, several as a zip (the video and its
    # world file in the plain base's own pixel grid).
    sent = capture_downloads(app)
    one = next(o for o in panel.download_pick.options if o.startswith("transforms"))
    assert ex.download(one)
    assert sent[-1] == ("transforms.json", (out / "transforms.json").read_bytes())
    mp4 = next(o for o in panel.download_pick.options if o.startswith("mp4"))
    assert ex.download(mp4)
    app.worker.wait_idle()
    import io
    import zipfile

    with zipfile.ZipFile(io.BytesIO(sent[-1][1])) as z:
        assert sorted(z.namelist()) == ["registered.mp4", "registered.wld"]
        assert z.read("registered.mp4") == (out / "registered.mp4").read_bytes()
    # Exporting again asks first and writes nothing yet ...
    before = (out / "transforms.json").stat().st_mtime_ns
    assert not ex.request(None, formats=["transforms"])
    assert ex.modal is not None and not app.jobs.busy
    assert (out / "transforms.json").stat().st_mtime_ns == before
    # ... "cancel" leaves everything; "new folder" writes exports-2; "overwrite" replaces.
    assert not ex.answer("cancel") and ex.modal is None
    assert not (app.project.folder / "exports-2").exists()
    ex.request(None, formats=["transforms"])
    assert ex.answer("new folder")
    app.jobs.join(60)
    assert (app.project.folder / "exports-2" / "transforms.json").exists()
    assert (out / "transforms.json").stat().st_mtime_ns == before
    ex.request(None, formats=["transforms"])
    assert ex.answer("overwrite")
    app.jobs.join(60)
    assert (out / "transforms.json").stat().st_mtime_ns != before
    # A map format asked for anyway (not through the disabled box) fails with the reason.
    assert run_export(app, ["geojson"])
    assert "needs a georeferenced base map" in panel.result_md.content


def test_georeferenced_base_exports_geotiff_points_geojson_and_cancels(open_registered, tif_base):
    import rasterio

    from registration.gis import read_points_file

    app = open_registered(tif_base)
    georef = app.inputs.base_georef
    assert georef is not None and georef.epsg == 32643
    seq = app.views["Sequence"]
    ex = seq.exporter
    assert not any(box.disabled for f, box in ex.panel.formats.items() if f != "traffic")
    assert ex.panel.formats["traffic"].disabled  # no traffic run
    assert "EPSG:32643" in ex.panel.georef_md.content
    assert run_export(app, ["geotiff", "points", "geojson"])
    out = app.project.folder / "exports"
    r = app.state.result
    # GeoTIFF frames in the map's CRS and pixel size, inside the map's bounds.
    with rasterio.open(out / "geotiff" / "000002.tif") as ds:
        assert ds.crs.to_epsg() == 32643 and ds.res == pytest.approx((0.5, 0.5))
        left, bottom, right, top = ds.bounds
    w, h = app.inputs.base_size
    assert 300000.0 <= left < right <= 300000.0 + 0.5 * w
    assert 3700000.0 - 0.5 * h <= bottom < top <= 3700000.0
    # .points of a frame: map coordinates of its control points (QGIS convention).
    pts = read_points_file(out / "points" / "000001.points")
    assert pts["crs"] and ("32643" in pts["crs"] or "UTM zone 43N" in pts["crs"])
    src, dst, kept, _ = r.control_points(1)
    ok = np.isfinite(r.lens.raw_from_corrected(src)).all(axis=1)
    assert np.allclose(pts["map"], georef.map_from_base(dst[ok]), atol=1e-6)
    # The frame's control-point table exports the same way (map side in map coordinates).
    seq.set_frame(1)
    app.worker.wait_idle()
    sent = capture_downloads(app)
    assert seq.export_points()
    table_pts = read_points_file(app.project.folder / "frame_000001.points")
    t = seq.table
    assert np.allclose(table_pts["map"], georef.map_from_base(t.base_xy), atol=1e-6)
    assert np.allclose(table_pts["source"], t.frame_xy, atol=1e-6)
    assert sent[-1][0] == "frame_000001.points"
    # GeoJSON in the map's CRS, several files offered as one zip.
    gj = json.loads((out / "footprints.geojson").read_text())
    assert len(gj["features"]) == 4 and "32643" in json.dumps(gj.get("crs"))
    label = next(o for o in ex.panel.download_pick.options if o.startswith("geojson"))
    assert "zip" in label and ex.download(label)
    app.worker.wait_idle()
    with zipfile.ZipFile(io.BytesIO(sent[-1][1])) as z:
        assert sorted(z.namelist()) == ["control_points.geojson", "footprints.geojson"]
    # Cancel: stopped after the first frame, what was written is kept and said so.
    on_progress = app.jobs._on_progress

    def cancel_after_first(job):
        on_progress(job)
        if job.name == "export" and job.done >= 1:
            app.jobs.request_cancel()

    app.jobs._on_progress = cancel_after_first
    ex.request(None, formats=["cog"])
    app.jobs.join(120)
    app.worker.wait_idle()
    assert "cancelled" in ex.panel.result_md.content
    assert len(list((out / "cog").glob("*.tif"))) == 1
