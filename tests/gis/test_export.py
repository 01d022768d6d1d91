"""Map coordinates through the result interface and the GIS exports of ``aerialreg export``, on a
small simulated sequence registered against a GeoTIFF base with a known transform and CRS; the
base's no-data mask in matching; the real orthophoto end to end."""

from __future__ import annotations

import ctypes
import glob
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS, Transformer

import registration
from app.cli import main as cli_main
from registration.coords import frame_outline
from registration.gis import (
    QGIS_POINTS_HEADER,
    ExportOptions,
    export_result,
    read_base_map,
    read_points_file,
    write_points_file,
)
from registration.gis.export import _Mosaic
from registration.global_registration import coarse_register, fine_register_reference
from registration.io import open_frames, read_image
from registration.run import get_preset
from registration.synth import SimConfig, load_truth, simulate
from tests.conftest import shared_data

# UTM 33N, 0.3 m pixels, north up: the synthetic base's known georeference.
TRANSFORM = (0.3, 0.0, 512345.25, 0.0, -0.3, 4123456.75)
EPSG = 32633


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    simulate(out, SimConfig(frame_size=(320, 240), n_frames=3, seed=1, video=False))
    base = read_image(out / "base.png")
    with rasterio.open(
        out / "base.tif", "w", driver="GTiff", width=base.shape[1], height=base.shape[0],
        count=3, dtype="uint8", crs=f"EPSG:{EPSG}", transform=Affine(*TRANSFORM),
        photometric="RGB",
    ) as ds:  # fmt: skip
        ds.write(np.moveaxis(base[..., ::-1], 2, 0))
    return out


def seed_arg(sim: Path) -> str:
    truth = load_truth(sim)
    w, h = truth.frame_size
    bx, by = truth.frame_to_base(0, [[w / 2, h / 2]])[0]
    return f"{w / 2},{h / 2},{bx},{by}"


@pytest.fixture(scope="module")
def result(sim, tmp_path_factory):
    """Registered through the CLI with the GeoTIFF base (read_base_map -> result.json)."""
    out = tmp_path_factory.mktemp("reg") / "out"
    args = ["register", "--base", str(sim / "base.tif"), "--frames", str(sim / "frames")]
    args += ["--out", str(out), "--gamma", str(load_truth(sim).gamma), "--seed", seed_arg(sim)]
    assert cli_main(args) == 0
    res = registration.load(out)
    assert all(r.status == "ok" for r in res.records)
    return res


def grid(w: int, h: int, n: int = 7) -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return np.c_[gx.ravel(), gy.ravel()]


# --------------------------------------------------------------------------------------------
# Map coordinates through the result interface


def test_result_records_georef_and_frame_to_map_is_the_affine_of_frame_to_base(result):
    meta = json.loads((result.out_dir / "result.json").read_text())
    assert meta["base_georef"]["transform"] == pytest.approx(list(TRANSFORM))
    assert CRS.from_wkt(meta["base_georef"]["crs_wkt"]).to_epsg() == EPSG
    pts = grid(*result.frame_size)
    a, b, c, d, e, f = TRANSFORM
    for k in range(result.n_frames):
        for stage in ("global", "local"):
            base = result.frame_to_base(k, pts, stage)
            expected = np.c_[a * (base[:, 0] + 0.5) + c, e * (base[:, 1] + 0.5) + f]
            got = result.frame_to_map(k, pts, stage)
            np.testing.assert_allclose(got, expected, atol=1e-9, rtol=0)
            back = result.map_to_frame(k, got, stage)
            np.testing.assert_allclose(back, pts, atol=1e-3)


def test_frame_to_map_in_wgs84_round_trips_under_a_millimetre(result):
    pts = grid(*result.frame_size, 5)
    utm = result.frame_to_map(1, pts)
    lonlat = result.frame_to_map(1, pts, to_crs="EPSG:4326")
    ref = Transformer.from_crs(EPSG, 4326, always_xy=True).transform(utm[:, 0], utm[:, 1])
    np.testing.assert_allclose(lonlat, np.c_[ref], atol=1e-12)
    back_utm = result.georef.from_crs(lonlat, "EPSG:4326")
    assert np.abs(back_utm - utm).max() < 1e-3  # metres
    raw = result.map_to_frame(1, lonlat, from_crs="EPSG:4326")
    assert np.abs(raw - pts).max() < 1e-3 / 0.3 + 1e-3  # a millimetre is 1/300 base pixel


def test_map_coordinates_nan_outside_and_error_without_georef(result, tmp_path):
    w, h = result.frame_size
    out = result.frame_to_map(0, [[w + 50, 10], [10, 10]], to_crs="EPSG:4326")
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()
    plain = tmp_path / "plain"
    plain.mkdir()
    meta = json.loads((result.out_dir / "result.json").read_text())
    meta["base_georef"] = None
    (plain / "result.json").write_text(json.dumps(meta))
    res = registration.load(plain)
    assert res.georef is None
    with pytest.raises(ValueError, match="not georeferenced"):
        res.frame_to_map(0, [[1, 2]])


# --------------------------------------------------------------------------------------------
# Exports


@pytest.fixture(scope="module")
def exported(result, sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    calls = []
    summary = export_result(
        result,
        out,
        "all",
        frames=open_frames(sim / "frames"),
        progress=lambda done, total: calls.append((done, total)),
    )
    return out, summary, calls


def pixel_of(transform: Affine, map_xy: np.ndarray) -> np.ndarray:
    """GDAL pixel/line (corner-based) of map points under a file's geotransform."""
    a, b, c, d, e, f = tuple(transform)[:6]
    inv = np.linalg.inv(np.array([[a, b], [d, e]]))
    return (np.asarray(map_xy) - (c, f)) @ inv.T


def test_exported_geotiffs_open_with_crs_and_corners_agree_with_frame_to_map(result, sim, exported):
    out, summary, _ = exported
    assert len(summary["files"]["geotiff"]) == result.n_frames
    frames = open_frames(sim / "frames")
    w, h = result.frame_size
    for k in range(result.n_frames):
        for fmt in ("geotiff", "cog"):
            with rasterio.open(out / fmt / f"{k:06d}.tif") as ds:
                assert ds.crs.to_epsg() == EPSG
                assert ds.res == pytest.approx((0.3, 0.3))
                image = np.moveaxis(ds.read(), 0, 2)[..., ::-1]
                mask = ds.dataset_mask() > 0
                transform = ds.transform
                bounds = ds.bounds
                assert (ds.overviews(1) != []) == (fmt == "cog")
        # The GeoTIFF's grid is the base's: a point's GeoTIFF pixel (from frame_to_map and the
        # file's own transform, GDAL's corner convention) is its base pixel minus a whole offset.
        corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
        tif_px = pixel_of(transform, result.frame_to_map(k, corners)) - 0.5
        offset = result.frame_to_base(k, corners) - tif_px
        np.testing.assert_allclose(offset, np.round(offset[:1]).repeat(4, 0), atol=1e-6)
        # The frame's outline (clipped to the base map) fits the bounds, with at most the 2 px
        # padding and rounding.
        wb, hb = result.base_size
        outline = result.frame_to_base(k, frame_outline(w, h)).clip(-0.5, (wb - 0.5, hb - 0.5))
        outline = result.georef.map_from_base(outline)
        lo, hi = outline.min(axis=0), outline.max(axis=0)
        assert bounds.left <= lo[0] < bounds.left + 4.5 * 0.3
        assert bounds.right - 4.5 * 0.3 < hi[0] <= bounds.right
        assert bounds.bottom <= lo[1] < bounds.bottom + 4.5 * 0.3
        assert bounds.top - 4.5 * 0.3 < hi[1] <= bounds.top
        # Content: the GeoTIFF pixel at frame_to_map(raw pixel) shows that raw pixel.
        raw = grid(w, h, 15)[::3] * 0.9 + [0.05 * w, 0.05 * h]
        ci, ri = np.round(pixel_of(transform, result.frame_to_map(k, raw)) - 0.5).astype(int).T
        assert mask[ri, ci].all()
        got = image[ri, ci].astype(float)
        frame = frames.get(k).astype(float)
        want = frame[np.round(raw[:, 1]).astype(int), np.round(raw[:, 0]).astype(int)]
        assert np.median(np.abs(got - want)) < 12


def test_png_world_file_and_mosaic_and_video(result, exported):
    out, summary, _ = exported
    with (
        rasterio.open(out / "png" / "000001.png") as png,
        rasterio.open(out / "geotiff" / "000001.tif") as tif,
    ):
        # GDAL reads the .pgw and the CRS from .aux.xml: the same grid as the GeoTIFF.
        assert png.crs.to_epsg() == EPSG
        assert tuple(png.transform) == pytest.approx(tuple(tif.transform))
        assert png.count == 4  # alpha = where the frame has data
    assert (out / "png" / "000001.prj").read_text().startswith("PROJCS[")
    x0, y0, bw, bh = summary["box"]
    with rasterio.open(out / "mosaic.tif") as ds:
        assert ds.crs.to_epsg() == EPSG and (ds.width, ds.height) == (bw, bh)
        assert ds.transform.c == pytest.approx(TRANSFORM[2] + 0.3 * x0)
        assert ds.overviews(1) and 0.3 < (ds.dataset_mask() > 0).mean() < 1.0
    import imageio.v2 as iio

    reader = iio.get_reader(out / "registered.mp4")
    try:
        assert reader.count_frames() == result.n_frames
        assert reader.get_meta_data()["size"] == (bw + bw % 2, bh + bh % 2)
    finally:
        reader.close()
    wld = [float(v) for v in (out / "registered.wld").read_text().split()]
    assert wld == pytest.approx(
        [0.3, 0, 0, -0.3, TRANSFORM[2] + 0.3 * (x0 + 0.5), TRANSFORM[5] - 0.3 * (y0 + 0.5)]
    )


def test_progress_counts_every_step_up_to_the_total(result, exported):
    _, summary, calls = exported
    totals = {t for _, t in calls}
    assert len(totals) == 1
    total = totals.pop()
    done = [d for d, _ in calls]
    assert done == list(range(total + 1))
    # Frames once each, the mosaic, and one step per non-raster format (points, transforms,
    # geojson, gpkg).
    assert total == result.n_frames + 1 + 4


def test_points_file_as_qgis_writes_it(result, exported):
    out, _, _ = exported
    path = out / "points" / "000000.points"
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#CRS: ")
    assert CRS.from_user_input(lines[0][len("#CRS: ") :]).to_epsg() == EPSG
    assert lines[1] == QGIS_POINTS_HEADER == "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[2:]])
    assert rows.shape[1] == 8 and len(rows) > 10
    assert (rows[:, 3] < 0).all() and (rows[:, 2] > 0).all()  # QGIS: y up from the top-left corner
    assert set(rows[:, 4]) <= {0.0, 1.0} and rows[:, 4].sum() > 0.5 * len(rows)
    np.testing.assert_allclose(rows[:, 7], np.hypot(rows[:, 5], rows[:, 6]))
    parsed = read_points_file(path)
    src, dst, kept, _ = result.control_points(0)
    raw = result.lens.raw_from_corrected(src)
    np.testing.assert_allclose(parsed["source"], raw, atol=1e-9)
    np.testing.assert_allclose(parsed["map"], result.georef.map_from_base(dst), atol=1e-6)
    np.testing.assert_array_equal(parsed["enable"], kept)


def test_points_source_convention_is_corner_based_with_y_up(tmp_path):
    path = write_points_file(
        tmp_path / "p.points", np.array([[0.0, 0.0], [9.0, 4.0]]), [[1, 2], [3, 4]], crs_wkt=None
    )
    lines = path.read_text().splitlines()
    assert lines[0] == QGIS_POINTS_HEADER
    assert lines[1].split(",")[2:4] == ["0.5", "-0.5"]
    assert lines[2].split(",")[2:4] == ["9.5", "-4.5"]


def _gdal_vector(path: Path) -> dict[str, tuple[int, str | None]]:
    """Layers of a vector file as GDAL's own drivers read it (through rasterio's libgdal):
    ``{layer: (feature count, EPSG code)}``."""
    libs = Path(rasterio.__file__).parent.parent / "rasterio.libs"
    found = glob.glob(str(libs / "libgdal*"))
    if not found:
        pytest.skip("rasterio's bundled libgdal not found (not a manylinux wheel)")
    g = ctypes.CDLL(found[0])
    g.GDALAllRegister()
    vp = ctypes.c_void_p
    g.GDALOpenEx.restype, g.GDALOpenEx.argtypes = vp, [ctypes.c_char_p, ctypes.c_uint, vp, vp, vp]
    g.GDALDatasetGetLayerCount.argtypes = [vp]
    g.GDALDatasetGetLayer.restype, g.GDALDatasetGetLayer.argtypes = vp, [vp, ctypes.c_int]
    g.OGR_L_GetFeatureCount.restype = ctypes.c_longlong
    g.OGR_L_GetFeatureCount.argtypes = [vp, ctypes.c_int]
    g.OGR_L_GetName.restype, g.OGR_L_GetName.argtypes = ctypes.c_char_p, [vp]
    g.OGR_L_GetSpatialRef.restype, g.OGR_L_GetSpatialRef.argtypes = vp, [vp]
    g.OSRGetAuthorityCode.restype = ctypes.c_char_p
    g.OSRGetAuthorityCode.argtypes = [vp, ctypes.c_char_p]
    g.GDALClose.argtypes = [vp]
    ds = g.GDALOpenEx(os.fsencode(path), 0x04, None, None, None)  # GDAL_OF_VECTOR
    assert ds, f"GDAL cannot open {path}"
    layers = {}
    try:
        for i in range(g.GDALDatasetGetLayerCount(ds)):
            lay = g.GDALDatasetGetLayer(ds, i)
            srs = g.OGR_L_GetSpatialRef(lay)
            code = g.OSRGetAuthorityCode(srs, None) if srs else None
            layers[g.OGR_L_GetName(lay).decode()] = (
                g.OGR_L_GetFeatureCount(lay, 1),
                code.decode() if code else None,
            )
    finally:
        g.GDALClose(ds)
    return layers


def test_geojson_and_geopackage_valid_in_map_coordinates(result, exported):
    out, _, _ = exported
    doc = json.loads((out / "control_points.geojson").read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["crs"]["properties"]["name"] == f"urn:ogc:def:crs:EPSG::{EPSG}"
    n_cps = sum(len(result.control_points(k)[0]) for k in range(result.n_frames))
    assert len(doc["features"]) == n_cps
    f0 = doc["features"][0]
    assert f0["type"] == "Feature" and f0["geometry"]["type"] == "Point"
    p = f0["properties"]
    np.testing.assert_allclose(
        f0["geometry"]["coordinates"], result.georef.map_from_base([[p["base_x"], p["base_y"]]])[0]
    )
    feet = json.loads((out / "footprints.geojson").read_text())["features"]
    assert len(feet) == result.n_frames
    ring = np.array(feet[0]["geometry"]["coordinates"][0])
    assert (ring[0] == ring[-1]).all() and len(ring) > 4
    # Area in m^2 of a footprint: the frame's ~ (320 x 240 px) at ~0.3 m x frame scale.
    assert 2000 < feet[0]["properties"]["area"] < 40000
    expected = {"control_points": (n_cps, str(EPSG)), "footprints": (result.n_frames, str(EPSG))}
    assert _gdal_vector(out / "control_points.geojson") == {
        "control_points": expected["control_points"]
    }
    assert _gdal_vector(out / "aerialreg.gpkg") == expected


def test_geojson_in_wgs84_and_marks_layer(result, sim, tmp_path):
    truth = load_truth(sim)
    # Mark the true images of two ground points in every frame.
    lines = ["point,frame,x,y"]
    for name, base_pt in (("A", [300.0, 280.0]), ("B", [420.0, 330.0])):
        for k in range(result.n_frames):
            x, y = truth.base_to_frame(k, [base_pt])[0]
            lines.append(f"{name},{k},{x},{y}")
    (tmp_path / "marks.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    args = ["export", str(result.out_dir), "--format", "geojson,gpkg", "--to", str(out)]
    args += ["--marks", str(tmp_path / "marks.csv"), "--vector-crs", "EPSG:4326", "--json"]
    assert cli_main(args) == 0
    doc = json.loads((out / "marks.geojson").read_text())
    assert "crs" not in doc  # RFC 7946: WGS 84 longitude, latitude
    means = [f for f in doc["features"] if f["properties"]["kind"] == "mean"]
    assert [f["properties"]["point"] for f in means] == ["A", "B"]
    lon, lat = means[0]["geometry"]["coordinates"]
    true_map = result.georef.map_from_base([[300.0, 280.0]])
    true_lonlat = result.georef.to_crs(true_map, "EPSG:4326")[0]
    # Registered within a pixel (0.3 m ~ 3e-6 degrees) of the truth; spread under a pixel.
    assert abs(lon - true_lonlat[0]) < 1e-5 and abs(lat - true_lonlat[1]) < 1e-5
    assert means[0]["properties"]["spread"] < 0.3
    assert _gdal_vector(out / "aerialreg.gpkg")["marks"] == (2 * result.n_frames + 2, "4326")


def test_transforms_json(result, exported):
    out, _, _ = exported
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["format"] == "aerialreg-transforms" and len(doc["frames"]) == result.n_frames
    w, h = result.frame_size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    for k, entry in enumerate(doc["frames"]):
        np.testing.assert_allclose(entry["corners_map"], result.frame_to_map(k, corners))
        hom = np.array(entry["map_from_raw_homography"])
        q = np.c_[corners, np.ones(4)] @ hom.T
        err = np.linalg.norm(q[:, :2] / q[:, 2:] - result.frame_to_map(k, corners), axis=1)
        # A homography cannot follow the lens and the field exactly; it says by how much.
        assert err.max() <= entry["homography_max_error_px"] * 0.3 * 1.5 + 1e-6
        assert entry["model"]["type"] == "PolyProjective"


def test_existing_files_need_force_and_bad_input_is_one_line(result, sim, tmp_path, capsys):
    out = tmp_path / "x"
    args = ["export", str(result.out_dir), "--format", "points", "--to", str(out)]
    assert cli_main(args) == 0
    capsys.readouterr()
    before = (out / "points" / "000000.points").stat().st_mtime_ns
    assert cli_main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0], err
    assert (out / "points" / "000000.points").stat().st_mtime_ns == before
    assert cli_main([*args, "--force"]) == 0
    assert cli_main(["export", str(result.out_dir), "--format", "shapefile"]) == 2
    assert "unknown export format 'shapefile'" in capsys.readouterr().err


def test_plain_base_allows_png_and_video_but_not_map_formats(result, sim, tmp_path, capsys):
    plain = tmp_path / "plain"
    plain.mkdir()
    meta = json.loads((result.out_dir / "result.json").read_text())
    meta["base_georef"] = None
    (plain / "result.json").write_text(json.dumps(meta))
    (plain / "frames").symlink_to(result.out_dir / "frames")
    res = registration.load(plain)
    with pytest.raises(ValueError, match="needs a georeferenced base map"):
        export_result(res, tmp_path / "o", ["geotiff"], frames=open_frames(sim / "frames"))
    summary = export_result(
        res, tmp_path / "o", ["png", "mp4", "points"], frames=open_frames(sim / "frames")
    )
    assert (tmp_path / "o" / "registered.mp4").is_file()
    # In the base image's own pixel grid (corner of pixel (0, 0) at (0, 0), rows along -y, as
    # QGIS shows an image without georeference): each PNG's world file puts it where it was
    # rendered, the video's too, and .points hold base px as the Seed view writes them.
    w, h = res.frame_size
    t = np.linspace(0, 1, 50)[:, None]
    border = np.concatenate([
        t * (w - 1, 0), (w - 1, 0) + t * (0, h - 1), (w - 1, h - 1) - t * (w - 1, 0),
        (0, h - 1) - t * (0, h - 1),
    ])  # fmt: skip
    for pgw in sorted((tmp_path / "o" / "png").glob("*.pgw")):
        a, d, b, e, c, f = (float(v) for v in pgw.read_text().split())
        assert (a, d, b, e) == (1.0, 0.0, 0.0, -1.0)
        alpha = cv2.imread(str(pgw.with_suffix(".png")), cv2.IMREAD_UNCHANGED)[..., 3] > 0
        # The frame's outline on the map, drawn into the crop where the world file places it
        # (c, f: the centre of the crop's pixel (0, 0), base pixel (c - 0.5, -f - 0.5)).
        outline = res.frame_to_base(int(pgw.stem), border) - (c - 0.5, -f - 0.5)
        drawn = np.zeros(alpha.shape, np.uint8)
        cv2.fillPoly(drawn, [np.round(outline).astype(np.int32)], 1)
        iou = (alpha & (drawn > 0)).sum() / (alpha | (drawn > 0)).sum()
        assert iou > 0.98, (pgw.name, iou)  # measured 0.995
    assert not list((tmp_path / "o").rglob("*.prj"))  # no CRS to write
    wld = [float(v) for v in (tmp_path / "o" / "registered.wld").read_text().split()]
    assert wld[:4] == [1.0, 0.0, 0.0, -1.0]
    pts = read_points_file(tmp_path / "o" / "points" / "000001.points")
    src, dst, kept, _ = res.control_points(1)
    assert pts["crs"] is None
    assert np.allclose(pts["map"], dst[: len(pts["map"])] * (1, -1) + (0.5, -0.5), atol=1e-9)
    # --format all of a plain base writes what it can, as the app's Export panel offers, and
    # says what it skipped; a map format asked for by name is refused.
    args = ["export", str(plain), "--frames", str(sim / "frames"), "--to", str(tmp_path / "all")]
    assert cli_main([*args, "--format", "all"]) == 0
    text = capsys.readouterr().out
    assert "skipped geotiff, cog, mosaic, geojson, gpkg: they need a georeferenced base" in text
    assert (tmp_path / "all" / "points").is_dir() and (tmp_path / "all" / "png").is_dir()
    assert cli_main([*args, "--format", "gpkg", "--force"]) == 2
    assert "needs a georeferenced base map" in capsys.readouterr().err
    # --georef supplies the georeference afterwards; it must match the base map's size.
    out = tmp_path / "g"
    assert (
        cli_main(
            [
                "export",
                str(plain),
                "--format",
                "geotiff",
                "--to",
                str(out),
                "--georef",
                str(sim / "base.tif"),
            ]
        )
        == 0
    )
    with rasterio.open(out / "geotiff" / "000000.tif") as ds:
        assert ds.crs.to_epsg() == EPSG
    assert summary["n_failed"] == 0


def test_median_mosaic_ignores_a_passing_car():
    """Three frames over one box: a bright 'car' in one frame disappears from the median."""
    rng = np.random.default_rng(3)
    ground = rng.integers(0, 200, (20, 30, 3)).astype(np.uint8)
    mosaic = _Mosaic((100, 50, 30, 20), "median")
    full = np.ones((20, 30), bool)
    car = ground.copy()
    car[5:10, 5:15] = 255
    mosaic.add(ground, full, (100, 50, 30, 20))
    mosaic.add(car, full, (100, 50, 30, 20))
    shifted = full.copy()
    shifted[:, :10] = False  # the third frame covers only the right part
    mosaic.add(ground, shifted, (100, 50, 30, 20))
    image, valid = mosaic.result()
    assert valid.all()
    np.testing.assert_array_equal(image[:, 10:], ground[:, 10:])
    # Two frames on the left: the median of two is their mean (rounded half up).
    expected = ((ground[:, :10].astype(int) + car[:, :10] + 1) // 2).astype(np.uint8)
    np.testing.assert_array_equal(image[:, :10], expected)


@pytest.mark.parametrize("method", ["median", "mean"])
def test_mosaic_equals_numpy_over_the_frames_with_data(method):
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 255, (30, 28, 3), dtype=np.uint8) for _ in range(7)]
    masks = [rng.random((30, 28)) < 0.6 for _ in range(7)]
    mosaic = _Mosaic((0, 0, 28, 30), method, max_frames=7)
    for image, mask in zip(images, masks, strict=True):
        mosaic.add(image, mask, (0, 0, 28, 30))
    got, valid = mosaic.result()
    stack = np.stack(
        [
            np.where(m[..., None], i.astype(float), np.nan)
            for i, m in zip(images, masks, strict=True)
        ]
    )
    have = np.isfinite(stack[..., 0]).any(axis=0)
    assert (valid == have).all() and not have.all()
    combine = np.nanmedian if method == "median" else np.nanmean
    want = np.floor(combine(stack[:, have], axis=0) + 0.5)
    np.testing.assert_array_equal(got[have], want)


def test_export_can_be_cancelled_after_a_frame(result, sim, tmp_path):
    import threading

    cancel = threading.Event()

    def progress(done, total):
        if done >= 1:
            cancel.set()

    summary = export_result(
        result,
        tmp_path,
        ["geotiff", "mp4"],
        frames=open_frames(sim / "frames"),
        options=ExportOptions(),
        progress=progress,
        cancel=cancel,
    )
    assert summary["cancelled"]
    assert len(list((tmp_path / "geotiff").glob("*.tif"))) == 1
    assert not (tmp_path / "registered.mp4").exists()
    assert not [p for p in tmp_path.rglob(".*") if p.is_file()]  # no temporary files left


# --------------------------------------------------------------------------------------------
# No-data in matching


def test_base_no_data_region_gets_no_control_points(tmp_path):
    """The base left of the middle coarse match declared no-data (its pixels left intact, so
    only the mask can keep matches out): without the mask control points land there, with it
    none do, and the registration still succeeds on the other half."""
    sim = tmp_path / "sim"
    simulate(sim, SimConfig(frame_size=(640, 480), n_frames=1, seed=1, video=False))
    truth = load_truth(sim)
    frame = read_image(sorted((sim / "frames").iterdir())[0])
    base = read_image(sim / "base.png")
    w, h = truth.frame_size
    seed = (w / 2, h / 2, *truth.frame_to_base(0, [[w / 2, h / 2]])[0])
    cfg = get_preset("default")
    coarse = coarse_register(
        frame, base, truth.gamma, seed, cfg.coarse, match_in=cfg.match_in, rng=0
    )
    fine = fine_register_reference(
        frame, base, truth.gamma, coarse, cfg.fine, match_in=cfg.match_in
    )
    cut = int(np.median(coarse.base_xy[coarse.inliers, 0]))
    assert (coarse.base_xy[coarse.inliers, 0] < cut).sum() >= 5
    assert (fine.dst[:, 0] < cut).sum() > 10
    valid = np.ones(base.shape[:2], bool)
    valid[:, :cut] = False
    coarse = coarse_register(
        frame, base, truth.gamma, seed, cfg.coarse, match_in=cfg.match_in, rng=0, base_valid=valid
    )
    assert coarse, coarse.reason
    fine = fine_register_reference(
        frame, base, truth.gamma, coarse, cfg.fine, match_in=cfg.match_in, base_valid=valid
    )
    assert fine, fine.reason
    # Coarse keypoints are found at 1/4 scale: up to 2 base px of sub-pixel slack at the edge.
    assert not (coarse.base_xy[:, 0] < cut - 2).any()
    assert not (fine.dst[:, 0] < cut - 0.5).any()
    # Accurate where the base has data (the rest is the model's extrapolation). The points
    # span half the frame, too little for the polyprojective's curvature over the whole frame,
    # so the fine step keeps the projective (measured median 1.37 px on the covered half; the
    # reference frame's field then takes up the rest in a run).
    assert fine.model_kind in ("projective", "affine", "similarity"), fine.model_reason
    pts = grid(w, h, 15)
    true_base = truth.frame_to_base(0, pts)
    err = np.linalg.norm(
        fine.base_from_corrected.apply(truth_corrected(truth, pts)) - true_base, axis=1
    )
    assert np.median(err[true_base[:, 0] > cut + 20]) < 1.8


def truth_corrected(truth, raw):
    from registration.lens import HarrisModel

    return HarrisModel(truth.gamma, *truth.frame_size).corrected_from_raw(raw)


def test_real_orthophoto_end_to_end(tmp_path):
    """Frames simulated over the real NUST orthophoto, registered against the GeoTIFF itself:
    map coordinates within a pixel of the truth where the map has data, no control point in its
    black collar, and a mosaic GeoTIFF in EPSG:32643."""
    path = shared_data("georef-orthophoto-nust", "ortho_utm43n_0.5m.tif")
    base = read_base_map(path)
    simulate(
        tmp_path / "sim",
        SimConfig(frame_size=(480, 360), n_frames=2, seed=2, video=False),
        scene=base.image[..., ::-1],
    )
    truth = load_truth(tmp_path / "sim")
    out = tmp_path / "reg"
    args = ["register", "--base", str(path), "--frames", str(tmp_path / "sim" / "frames")]
    args += ["--out", str(out), "--gamma", str(truth.gamma), "--seed", seed_arg(tmp_path / "sim")]
    assert cli_main(args) == 0
    res = registration.load(out)
    assert res.georef.epsg == 32643
    pts = grid(*truth.frame_size, 15)
    for k in range(res.n_frames):
        true_base = truth.frame_to_base(k, pts)
        ij = np.round(true_base).astype(int)
        inside = base.valid[ij[:, 1].clip(0, 1778), ij[:, 0].clip(0, 1808)]
        err_m = np.linalg.norm(
            res.frame_to_map(k, pts) - base.georef.map_from_base(true_base), axis=1
        )
        assert np.median(err_m[inside]) < 0.5  # metres = one 0.5 m pixel
        dst = res.control_points(k)[1]
        d = np.round(dst).astype(int)
        assert base.valid[d[:, 1], d[:, 0]].all()
    summary = export_result(res, tmp_path / "exp", ["mosaic", "points"])
    with rasterio.open(summary["files"]["mosaic"][0]) as ds:
        assert ds.crs.to_epsg() == 32643 and ds.res == pytest.approx((0.5, 0.5))


def test_export_benchmark_runs_end_to_end(capsys):
    assert cli_main(["bench", "export", "--size", "480x360", "--frames", "2", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)["export"]
    ratios = figures["per_frame_ratio"]
    assert ratios["cv2.imwrite PNG (baseline)"] == pytest.approx(1.0)
    assert all(v > 0 for v in ratios.values()) and figures["n_frames"] == 2
    assert figures["export_total_s"] > 0 and "| per frame |" in figures["markdown"]
