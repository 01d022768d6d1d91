"""Georeferenced base maps: the half-pixel convention against GDAL, world files, palette / 16-bit /
alpha / no-data conversions, other CRSs through pyproj, and the real NUST orthophoto."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS, Transformer
from rasterio.transform import xy as rio_xy

from registration.gis import (
    GeoReference,
    find_world_file,
    read_base_map,
    read_georeference,
    read_world_file,
    stretch_to_uint8,
    world_file_text,
)
from tests.conftest import shared_data

UTM33 = CRS.from_epsg(32633).to_wkt()
# A rotated, sheared, non-square pixel grid: any half-pixel slip shows in both axes.
ROTATED = (0.30, 0.05, 500123.25, 0.04, -0.32, 4100456.75)


def write_tif(path, bands, transform=None, crs="EPSG:32633", **kw):
    bands = np.asarray(bands)
    if bands.ndim == 2:
        bands = bands[None]
    profile = dict(
        driver="GTiff",
        width=bands.shape[2],
        height=bands.shape[1],
        count=bands.shape[0],
        dtype=bands.dtype.name,
        **kw,
    )
    if transform is not None:
        profile.update(transform=Affine(*transform), crs=crs)
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(bands)
        return ds


def test_half_pixel_convention_matches_gdal(tmp_path):
    """Base pixel (x, y) (centre at integers) is at A * (x + 0.5, y + 0.5): GDAL's own pixel
    centres (rasterio ``xy(..., offset="center")``) agree to 1e-9, and the inverse comes back."""
    path = tmp_path / "rot.tif"
    write_tif(path, np.zeros((3, 40, 50), np.uint8) + 100, ROTATED)
    georef = read_base_map(path).georef
    assert georef.transform == pytest.approx(ROTATED, abs=1e-12)
    assert CRS.from_wkt(georef.crs_wkt).to_epsg() == 32633
    rows, cols = np.meshgrid(np.arange(0, 40, 7), np.arange(0, 50, 9), indexing="ij")
    gx, gy = rio_xy(Affine(*ROTATED), rows.ravel(), cols.ravel(), offset="center")
    ours = georef.map_from_base(np.c_[cols.ravel(), rows.ravel()])
    np.testing.assert_allclose(ours, np.c_[gx, gy], atol=1e-9, rtol=0)
    # Pixel (0, 0)'s centre is half a pixel in from the corner the transform names.
    a, b, c, d, e, f = ROTATED
    np.testing.assert_allclose(
        georef.map_from_base([[0, 0]])[0], [c + 0.5 * a + 0.5 * b, f + 0.5 * d + 0.5 * e]
    )
    # The corner of the image is at base (-0.5, -0.5).
    np.testing.assert_allclose(georef.map_from_base([[-0.5, -0.5]])[0], [c, f], atol=1e-9)
    pts = np.array([[0.0, 0.0], [12.25, 33.5], [-3.0, 47.75]])
    np.testing.assert_allclose(georef.base_from_map(georef.map_from_base(pts)), pts, atol=1e-9)


def test_world_file_round_trip_and_gdal_reads_it_the_same(tmp_path):
    """A world file stores the centre of pixel (0, 0); writing and reading it is exact, and GDAL
    (reading the same .pgw beside a PNG) derives the same corner transform."""
    import cv2

    text = world_file_text(ROTATED)
    a, b, c, d, e, f = ROTATED
    lines = [float(v) for v in text.split()]
    assert lines == pytest.approx([a, d, b, e, c + 0.5 * a + 0.5 * b, f + 0.5 * d + 0.5 * e])
    png = tmp_path / "map.png"
    cv2.imwrite(str(png), np.full((30, 40, 3), 90, np.uint8))
    (tmp_path / "map.pgw").write_text(text)
    assert find_world_file(png) == tmp_path / "map.pgw"
    assert read_world_file(tmp_path / "map.pgw") == pytest.approx(ROTATED, abs=1e-9)
    with rasterio.open(png) as ds:
        assert tuple(ds.transform)[:6] == pytest.approx(ROTATED, abs=1e-9)
    # Without a .prj the map has a transform but no CRS; a .prj or an explicit CRS adds it.
    base = read_base_map(png)
    assert base.georef.transform == pytest.approx(ROTATED, abs=1e-9)
    assert base.georef.crs_wkt is None
    assert CRS.from_wkt(read_base_map(png, crs="EPSG:32633").georef.crs_wkt).to_epsg() == 32633
    (tmp_path / "map.prj").write_text(CRS.from_epsg(32633).to_wkt("WKT1_ESRI"))
    assert CRS.from_wkt(read_base_map(png).georef.crs_wkt).to_epsg() == 32633
    georef, size = read_georeference(png)
    assert size == (40, 30) and georef.transform == pytest.approx(ROTATED, abs=1e-9)


def test_bad_world_file_and_crs_are_one_line_errors(tmp_path):
    import cv2

    png = tmp_path / "map.jpg"
    cv2.imwrite(str(png), np.full((30, 40, 3), 90, np.uint8))
    with pytest.raises(ValueError, match="no world file"):
        read_base_map(png, crs="EPSG:32633")
    (tmp_path / "map.jgw").write_text("0.5\n0\n0\n-0.5\n100\n")
    with pytest.raises(ValueError, match=r"map\.jgw must hold six numbers, got 5"):
        read_base_map(png)
    (tmp_path / "map.jgw").write_text("0.5\n0\n0\n-0.5\n100\n200\n")
    with pytest.raises(ValueError, match="not a coordinate reference system: 'EPSG:99999999'"):
        read_base_map(png, crs="EPSG:99999999")


def test_to_crs_wgs84_round_trip_under_a_millimetre():
    georef = GeoReference(ROTATED, UTM33)
    base = np.array([[0.0, 0.0], [1000.5, 2000.25], [-50.0, 70.0]])
    utm = georef.map_from_base(base)
    lonlat = georef.to_crs(utm, "EPSG:4326")
    # (longitude, latitude) order whatever EPSG:4326's official axis order.
    expected = Transformer.from_crs(32633, 4326, always_xy=True).transform(utm[:, 0], utm[:, 1])
    np.testing.assert_allclose(lonlat, np.c_[expected], atol=1e-12)
    assert 14 < lonlat[0, 0] < 16 and 36 < lonlat[0, 1] < 38
    back = georef.from_crs(lonlat, "EPSG:4326")
    assert np.abs(back - utm).max() < 1e-3
    np.testing.assert_allclose(georef.base_from_map(back), base, atol=1e-3 / 0.3)
    with pytest.raises(ValueError, match="CRS is unknown"):
        GeoReference(ROTATED).to_crs(utm, "EPSG:4326")


def test_georeference_dict_crop_and_scale():
    georef = GeoReference(ROTATED, UTM33)
    assert GeoReference.from_dict(georef.to_dict()) == georef
    assert georef.to_dict()["epsg"] == 32633 and georef.units == "metre"
    crop = georef.cropped(17, 5)
    np.testing.assert_allclose(
        crop.map_from_base([[0, 0], [3.5, 2]]), georef.map_from_base([[17, 5], [20.5, 7]])
    )
    half = georef.scaled(0.5)
    # The outer corner stays; pixel (0, 0) of the half-size image covers base pixels 0..1.
    np.testing.assert_allclose(
        half.map_from_base([[-0.5, -0.5]]), georef.map_from_base([[-0.5, -0.5]])
    )
    np.testing.assert_allclose(half.map_from_base([[0, 0]]), georef.map_from_base([[0.5, 0.5]]))
    assert GeoReference(ROTATED, "EPSG:32633") == georef  # stored as WKT
    assert GeoReference(ROTATED, 32633).epsg == 32633
    with pytest.raises(ValueError, match="singular"):
        GeoReference((0, 0, 1, 0, 0, 1))


def test_palette_geotiff_via_colour_table_and_black_collar(tmp_path):
    """Palette indices go through the colour table; index 0 is black: the collar touching the
    border becomes no-data, a black patch inside the map stays valid."""
    index = np.full((60, 80), 3, np.uint8)
    index[:, :10] = 0  # collar on the left edge
    index[25:35, 40:50] = 0  # dark patch inside
    index[5:15, 20:30] = 7
    cmap = {0: (0, 0, 0, 255), 3: (200, 150, 100, 255), 7: (10, 20, 30, 255)}
    path = tmp_path / "pal.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=80, height=60, count=1, dtype="uint8",
        crs="EPSG:32633", transform=Affine(*ROTATED), photometric="palette",
    ) as ds:  # fmt: skip
        ds.write(index, 1)
        ds.write_colormap(1, cmap)
    base = read_base_map(path)
    assert base.image.shape == (60, 80, 3)
    np.testing.assert_array_equal(base.image[0, 50], (100, 150, 200))  # BGR of (200, 150, 100)
    np.testing.assert_array_equal(base.image[8, 25], (30, 20, 10))
    assert not base.valid[:, :10].any()
    assert base.valid[25:35, 40:50].all() and base.valid[:, 10:].all()
    assert any("palette" in n for n in base.notes)
    # With only the file's declarations, nothing is masked; a no-data index masks it anywhere.
    assert read_base_map(path, nodata="file").valid.all()
    explicit = read_base_map(path, nodata=0)
    assert not explicit.valid[25:35, 40:50].any() and not explicit.valid[:, :10].any()


def test_16bit_robust_stretch_same_map_for_all_bands(tmp_path):
    rng = np.random.default_rng(7)
    data = rng.integers(1000, 5000, (3, 50, 60)).astype(np.uint16)
    data[1] += 2000  # green brighter: the common stretch keeps that balance
    data[:, 0, :5] = 65535  # hot pixels
    path = tmp_path / "u16.tif"
    write_tif(path, data, ROTATED, photometric="RGB")
    base = read_base_map(path)
    lo, hi = np.percentile(data.astype(float), [0.5, 99.5])
    expected = np.clip((data.astype(float) - lo) * 255 / (hi - lo) + 0.5, 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(base.image, np.moveaxis(expected, 0, 2)[..., ::-1])
    assert (base.image[0, :5] == 255).all()
    assert base.image[..., 1].mean() > base.image[..., 2].mean() + 60
    assert any("uint16" in n for n in base.notes)
    img, (lo2, hi2) = stretch_to_uint8(np.array([[[0.0, 0.5, 1.0, np.nan]]]))
    assert img.shape == (1, 1, 4) and (lo2, hi2) == pytest.approx((0.005, 0.995))


def test_alpha_band_and_nodata_tag_become_invalid(tmp_path):
    rgba = np.full((4, 30, 40), 120, np.uint8)
    rgba[3] = 255
    rgba[3, 10:20, 10:20] = 0
    path = tmp_path / "rgba.tif"
    write_tif(path, rgba, ROTATED, photometric="RGB", alpha="YES")
    base = read_base_map(path)
    assert base.image.shape == (30, 40, 3)
    assert not base.valid[10:20, 10:20].any() and base.valid.sum() == 30 * 40 - 100
    grey = np.full((30, 40), 80, np.uint16)
    grey[:, 30:] = 9999
    path = tmp_path / "nodata.tif"
    write_tif(path, grey, ROTATED, nodata=9999)
    base = read_base_map(path)
    assert not base.valid[:, 30:].any() and base.valid[:, :30].all()
    assert (base.image[:, :30] == base.image[0, 0]).all() and base.image.shape[2] == 3


def test_plain_png_without_world_file_is_a_plain_base(tmp_path):
    import cv2

    img = np.zeros((30, 40, 4), np.uint8)
    img[..., :3] = 77
    img[..., 3] = 255
    img[:5, :5, 3] = 0
    cv2.imwrite(str(tmp_path / "plain.png"), img)
    base = read_base_map(tmp_path / "plain.png")
    assert base.georef is None
    assert not base.valid[:5, :5].any() and base.valid.sum() == 30 * 40 - 25
    with pytest.raises(FileNotFoundError):
        read_base_map(tmp_path / "missing.tif")
    (tmp_path / "junk.tif").write_bytes(b"not a tiff at all")
    with pytest.raises(ValueError, match="not a readable raster"):
        read_base_map(tmp_path / "junk.tif")


def test_real_orthophoto_palette_utm43n_with_black_collar():
    """The real NUST orthophoto (../shared): palette colours, EPSG:32643, 0.5 m pixels, black
    (palette) fill around a rotated valid area without a no-data tag."""
    path = shared_data("georef-orthophoto-nust", "ortho_utm43n_0.5m.tif")
    base = read_base_map(path)
    georef = base.georef
    assert base.size == (1809, 1779)
    assert georef.epsg == 32643 and georef.units == "metre"
    assert georef.transform == pytest.approx((0.5, 0, 313101.47628, 0, -0.5, 3724912.30675))
    with rasterio.open(path) as ds:
        index = ds.read(1)
        cmap = ds.colormap(1)
    y, x = 900, 900
    np.testing.assert_array_equal(base.image[y, x], cmap[int(index[y, x])][2::-1])
    # The corners are fill, the centre is ground; about a third of the map is collar.
    assert not base.valid[[0, 0, -1, -1], [0, -1, 0, -1]].any()
    assert base.valid[880:920, 880:920].all()
    assert 0.55 < base.valid.mean() < 0.75
    # No valid pixel is pure fill on the collar's edge, and dark ground inside stays valid.
    dark_inside = (base.image.max(axis=2) < 30) & base.valid
    assert dark_inside.sum() > 0
    lon, lat = georef.to_crs(georef.map_from_base([[x, y]]), "EPSG:4326")[0]
    assert 72.9 < lon < 73.1 and 33.6 < lat < 33.7  # Islamabad


def test_plain_colour_base_reads_as_the_same_bgr_pixels_as_a_frame(tmp_path):
    """A PNG base without a world file is the plain image, in OpenCV's BGR order like every
    other image of the pipeline (a swapped channel order changes every grey level)."""
    import cv2

    from registration.gis import read_base_map
    from registration.io import read_image

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    img[0, 0] = (255, 0, 0)  # pure blue in BGR
    path = tmp_path / "base.png"
    cv2.imwrite(str(path), img)
    bm = read_base_map(path)
    np.testing.assert_array_equal(bm.image, read_image(path))
    np.testing.assert_array_equal(bm.image[0, 0], (255, 0, 0))
    assert bm.georef is None


def test_impossible_geographic_georeferences_are_refused(tmp_path):
    """A map in local metres tagged WGS 84 (0.182 'degree' pixels reaching latitude 92.8°, the
    issue's case) is refused in one line naming the figures; a grid in real degrees over
    Islamabad reads, and so do the metres with the CRS they are really in."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (3, 510, 600), dtype=np.uint8)
    bad = write_tif(tmp_path / "metres.tif", img, (0.182, 0, 0.0, 0, -0.182, 92.8), "EPSG:4326")
    with pytest.raises(ValueError) as exc:
        read_base_map(bad.name)
    msg = str(exc.value)
    assert "\n" not in msg and "metres.tif" in msg and "pixels are 0.182 degrees" in msg
    assert "latitude -0.02..92.8" in msg and "--base-crs" in msg
    with pytest.raises(ValueError, match="not degrees"):
        read_georeference(bad.name)
    good = write_tif(tmp_path / "deg.tif", img, (2e-6, 0, 73.0, 0, -2e-6, 33.64), "EPSG:4326")
    assert read_base_map(good.name).georef.crs.is_geographic
    # The same metres, with the CRS they are really in, read; or, with CRS "none", as a plain
    # image without a georeference.
    assert read_base_map(bad.name, crs="EPSG:32643").georef.epsg == 32643
    plain = read_base_map(bad.name, crs="none")
    assert plain.georef is None and "georeference ignored (CRS none)" in plain.notes
    assert read_georeference(bad.name, crs="None") == (None, (600, 510))


@pytest.mark.parametrize(
    "crs, kind",
    [
        ("EPSG:5703", "Vertical CRS"),
        ("EPSG:4978", "Geocentric CRS"),
        ("EPSG:4979", "Geographic 3D CRS"),
        ("EPSG:7405", "Compound CRS"),
    ],
)
def test_only_horizontal_2d_crs_are_accepted_for_a_base_map(tmp_path, crs, kind):
    img = np.full((3, 40, 50), 120, np.uint8)
    path = write_tif(tmp_path / "m.tif", img, ROTATED).name
    with pytest.raises(ValueError) as exc:
        read_base_map(path, crs=crs)
    msg = str(exc.value)
    assert "\n" not in msg and crs in msg and f"is a {kind}" in msg
    assert "horizontal projected or geographic" in msg
