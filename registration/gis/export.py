"""GIS exports of a registration result with a georeferenced base map.

One entry point, :func:`export_result`, writes any of :data:`FORMATS` into a folder, rendering each
frame once for all raster formats; the writers it uses are public for single files
(:func:`write_geotiff`, :func:`write_png_georeferenced`; the vector ones are in
:mod:`registration.gis.vector`).

Files in the output folder (``KKKKKK`` = frame index, 6 digits; failed frames are left out of the
per-frame formats, and black in the video):

* ``geotiff/KKKKKK.tif``: registered frame, RGB, tiled, deflate, internal no-data mask, CRS;
* ``cog/KKKKKK.tif``: the same as cloud-optimised GeoTIFF (GDAL's COG driver, with overviews);
* ``png/KKKKKK.png`` + ``.pgw`` world file + ``.prj`` and ``.png.aux.xml`` (the CRS for ESRI
  tools and for GDAL/QGIS); alpha = where the frame has data;
* ``mosaic.tif``: the sequence's mosaic (per-pixel median of up to ``mosaic_frames`` frames
  spread over the sequence, so moving vehicles vanish; or the mean of all), as COG;
* ``registered.mp4`` + ``registered.wld``/``.prj``: the registered video over the sequence's
  footprint (the world file maps video pixels to map coordinates, for every frame);
* ``points/KKKKKK.points``: the frame's control points for QGIS's georeferencer
  (:func:`registration.gis.vector.write_points_file`);
* ``transforms.json``: per-frame transforms (:func:`transforms_document`);
* ``control_points.geojson``, ``footprints.geojson`` (+ ``marks.geojson`` with hand-marked
  evaluation points): map coordinates (:func:`registration.gis.vector.write_geojson`);
* ``aerialreg.gpkg``: the same three layers in one GeoPackage.

With a plain base map (no georeference) the PNGs' and the video's world files and the
``.points`` files are in the base image's own pixel grid (:data:`registration.gis.georef.
PIXEL_GRID`, as QGIS shows an image without georeference), and :data:`MAP_FORMATS` are refused.

Registered frames are cropped to their own footprint (``crop="frame"``) or all to the
sequence's (``crop="sequence"``, one grid for all). Every file is written to a temporary name and
renamed, so a reader never sees half a file; existing files are an error unless ``force``.
"""

from __future__ import annotations

import copy
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.errors import FilesExist, NotGeoreferenced
from registration.gis.georef import (
    PIXEL_GRID,
    GeoReference,
    aux_xml_text,
    esri_wkt,
    parse_crs,
    world_file_text,
)
from registration.gis.vector import (
    control_point_layer,
    footprint_layer,
    marks_layer,
    write_geojson,
    write_geopackage,
    write_points_files,
)
from registration.io import (
    atomic_path,
    check_not_an_input,
    check_result_frames,
    input_locations,
    temp_target,
    write_bytes_atomic,
    write_image_atomic,
    write_json_atomic,
)

Progress = Callable[[int, int], None]

FORMATS: dict[str, str] = {
    "geotiff": "registered frames as GeoTIFF (tiled, deflate, no-data mask, CRS)",
    "cog": "registered frames as cloud-optimised GeoTIFF (with overviews)",
    "png": "registered frames as PNG with world file (.pgw) and CRS sidecars (.prj, .aux.xml)",
    "mosaic": "one mosaic of the sequence (median or mean of the registered frames) as COG",
    "mp4": "registered video over the sequence footprint, with a world file (.wld)",
    "points": "control points per frame as QGIS georeferencer .points files",
    "transforms": "per-frame transforms as JSON (models, corners, homography approximations)",
    "geojson": "control points, frame footprints (and hand-marked points) as GeoJSON",
    "gpkg": "control points, frame footprints (and hand-marked points) as one GeoPackage",
}
# Formats that need the frames' pixels.
RASTER_FORMATS = ("geotiff", "cog", "png", "mosaic", "mp4")
# Formats that need map coordinates (a georeferenced base).
MAP_FORMATS = ("geotiff", "cog", "mosaic", "geojson", "gpkg")
COMPRESSIONS = ("deflate", "lzw", "zstd", "none")


@dataclass(frozen=True)
class ExportOptions:
    """What :func:`export_result` writes and how.

    Attributes:
        stage: ``"local"`` (global model + displacement field) or ``"global"``.
        crop: ``"frame"`` (each registered frame cropped to its own footprint) or
            ``"sequence"`` (every frame on the sequence's footprint grid).
        compress: GeoTIFF compression, one of :data:`COMPRESSIONS`.
        mosaic: ``"median"`` (per pixel, of ``mosaic_frames`` frames spread evenly over the
            sequence: moving vehicles vanish) or ``"mean"`` (of every frame).
        mosaic_frames: frames in a median mosaic (memory: this many frame footprints).
        fps: frames per second of the video (paper: ~5).
        video_scale: resize factor of the video (e.g. 0.5 for a quarter of the pixels).
        vector_crs: CRS of GeoJSON/GeoPackage coordinates; None = the base's CRS (GeoJSON then
            carries a ``crs`` member as GDAL writes it); ``"EPSG:4326"`` = RFC 7946 longitude,
            latitude.
        step: the registration mapping is evaluated every ``step`` px when rendering.
        force: overwrite existing files.
    """

    stage: str = "local"
    crop: str = "frame"
    compress: str = "deflate"
    mosaic: str = "median"
    mosaic_frames: int = 15
    fps: float = 5.0
    video_scale: float = 1.0
    vector_crs: str | None = None
    step: int = 8
    force: bool = False

    def validate(self) -> None:
        choices = {
            "stage": ("global", "local"),
            "crop": ("frame", "sequence"),
            "compress": COMPRESSIONS,
            "mosaic": ("median", "mean"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.mosaic_frames < 1:
            raise ValueError(f"mosaic_frames must be at least 1, got {self.mosaic_frames}")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not 0 < self.video_scale <= 4:
            raise ValueError(f"video_scale must be in (0, 4], got {self.video_scale}")
        if self.step < 1:
            raise ValueError(f"step must be at least 1, got {self.step}")
        if self.vector_crs is not None:
            parse_crs(self.vector_crs)  # ValueError naming it, before anything is written


# --------------------------------------------------------------------------------------------
# Single-file writers


def write_geotiff(
    path: str | os.PathLike,
    image: NDArray[np.uint8],
    georef: GeoReference | None,
    *,
    mask: NDArray[np.bool_] | None = None,
    cog: bool = False,
    compress: str = "deflate",
    num_threads: int | None = None,
) -> Path:
    """Write a BGR (or grey) uint8 image as a GeoTIFF, atomically.

    Args:
        path: output ``.tif``.
        image: ``(H, W, 3)`` BGR or ``(H, W)`` grey uint8, as OpenCV holds it.
        georef: transform and CRS of the image's pixel grid (None: a plain TIFF).
        mask: ``(H, W)`` bool, where the image has data; stored as GDAL's internal mask band
            (QGIS shows the rest transparent). None or all True: no mask.
        cog: cloud-optimised GeoTIFF (GDAL's COG driver: tiled, with overviews).
        compress: one of :data:`COMPRESSIONS` (with horizontal predictor for deflate/lzw/zstd).
        num_threads: compression threads (GDAL ``NUM_THREADS``); None = GDAL's default (one).
    """
    import rasterio

    if compress not in COMPRESSIONS:
        raise ValueError(f"compress must be one of {', '.join(COMPRESSIONS)}, got {compress!r}")
    path = Path(path)
    bands = image[None] if image.ndim == 2 else np.moveaxis(image[..., ::-1], 2, 0)
    h, w = image.shape[:2]
    profile: dict[str, Any] = {
        "driver": "COG" if cog else "GTiff",
        "width": w,
        "height": h,
        "count": bands.shape[0],
        "dtype": "uint8",
    }
    if georef is not None:
        profile["transform"] = georef.affine
        if georef.crs_wkt is not None:
            profile["crs"] = rasterio.crs.CRS.from_wkt(georef.crs_wkt)
    if compress != "none":
        profile.update(compress=compress, predictor=2)
    if not cog:
        profile.update(tiled=True, blockxsize=512, blockysize=512)
        if bands.shape[0] == 3:
            profile["photometric"] = "RGB"
    if num_threads:
        profile["num_threads"] = int(num_threads)
    use_mask = mask is not None and not np.all(mask)
    with atomic_path(path) as tmp, rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        with rasterio.open(tmp, "w", **profile) as ds:
            ds.write(bands)
            if use_mask:
                ds.write_mask(np.asarray(mask, bool).astype(np.uint8) * 255)
    return path


def write_png_georeferenced(
    path: str | os.PathLike,
    image: NDArray[np.uint8],
    georef: GeoReference | None,
    *,
    mask: NDArray[np.bool_] | None = None,
) -> list[Path]:
    """A PNG (alpha = ``mask``) with its world file (``.pgw``) and, with a CRS, ``.prj`` (ESRI
    WKT) and ``.png.aux.xml`` (GDAL reads the CRS of a PNG from there). Returns the paths."""
    path = Path(path)
    out = image
    if mask is not None and not np.all(mask):
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        out = np.dstack([bgr, np.asarray(mask, bool).astype(np.uint8) * 255])
    write_image_atomic(path, out)
    written = [path]
    if georef is not None:
        written += write_world_files(path, georef, world_suffix=".pgw")
    return written


def write_world_files(
    path: Path, georef: GeoReference, *, world_suffix: str, aux: bool = True
) -> list[Path]:
    """World file (``path`` with ``world_suffix``) and CRS sidecars: ``.prj`` and, with ``aux``,
    ``<name>.aux.xml``."""
    written = [path.with_suffix(world_suffix)]
    write_bytes_atomic(written[0], world_file_text(georef.transform).encode())
    if georef.crs_wkt is not None:
        prj = path.with_suffix(".prj")
        write_bytes_atomic(prj, esri_wkt(georef.crs_wkt).encode())
        written.append(prj)
        if aux:
            written.append(Path(str(path) + ".aux.xml"))
            write_bytes_atomic(written[-1], aux_xml_text(georef.crs_wkt).encode())
    return written


# --------------------------------------------------------------------------------------------
# Transforms


def _homography(src: NDArray, dst: NDArray) -> tuple[NDArray | None, float]:
    ok = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
    if ok.sum() < 4:
        return None, math.nan
    h, _ = cv2.findHomography(src[ok], dst[ok], 0)
    if h is None:
        return None, math.nan
    q = np.c_[src[ok], np.ones(ok.sum())] @ h.T
    err = np.linalg.norm(q[:, :2] / q[:, 2:] - dst[ok], axis=1)
    return h / h[2, 2], float(err.max())


def transforms_document(result, georef: GeoReference | None, stage: str = "local") -> dict:
    """Per-frame transforms, JSON-ready.

    For each frame: ``status``; ``model`` (the global ``base_from_corrected`` polyprojective
    exactly as the result stores it; corrected pixels come from raw ones through the Harris
    model given at the top); ``corners_raw`` -> ``corners_base`` (and ``corners_map``) at
    ``stage``; and ``base_from_raw_homography`` (and ``map_from_raw_homography``): the 3x3
    homography closest (least squares over a 17x13 grid of raw pixels, pixel centres at
    integers) to the whole mapping at ``stage``, with its largest error over the grid in base
    pixels, for tools that only know homographies.
    """
    w, h = result.frame_size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    grid = np.c_[gx.ravel(), gy.ravel()]
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    frames = []
    for k in range(result.n_frames):
        rec = result.records[k]
        entry: dict[str, Any] = {"frame": k, "status": rec.status}
        if not rec.ok:
            entry["reason"] = rec.reason
            frames.append(entry)
            continue
        base = result.frame_to_base(k, grid, stage)
        hom, err = _homography(grid, base)
        entry["model"] = rec.model
        entry["corners_raw"] = corners.tolist()
        entry["corners_base"] = _json_points(result.frame_to_base(k, corners, stage))
        entry["base_from_raw_homography"] = None if hom is None else hom.tolist()
        entry["homography_max_error_px"] = err if math.isfinite(err) else None
        if georef is not None:
            entry["corners_map"] = _json_points(
                georef.map_from_base(result.frame_to_base(k, corners, stage))
            )
            hm, _ = _homography(grid, georef.map_from_base(base))
            entry["map_from_raw_homography"] = None if hm is None else hm.tolist()
        frames.append(entry)
    lens = result.lens
    return {
        "format": "aerialreg-transforms",
        "version": 1,
        "stage": stage,
        "pixel_convention": "pixel centres at integer coordinates; (0,0) = top-left pixel",
        "frame_size": list(result.frame_size),
        "base_size": list(result.base_size),
        "harris": {
            "gamma": float(result.gamma),
            "k2": float(result.camera.k2),
            "centre": [float(v) for v in lens.c],
            "r_n": float(lens.r_n),
            "corrected_from_raw": "Harris model of conventions.md with -gamma"
            if not result.camera.k2
            else "rho = rho' / sqrt(1 - gamma rho'^2 - k2 rho'^4), radii normalised by r_n about "
            "the centre (the Harris model of conventions.md plus a fourth-order term)",
        },
        "base_georef": None if georef is None else georef.to_dict(),
        "frames": frames,
    }


def _json_points(p: NDArray) -> list:
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in np.asarray(p)]


# --------------------------------------------------------------------------------------------
# The whole result


def resolve_formats(formats) -> list[str]:
    """Validated, de-duplicated format names (``"all"`` = every format)."""
    names = [f.strip().lower() for f in ([formats] if isinstance(formats, str) else formats)]
    if "all" in names:
        return list(FORMATS)
    unknown = [f for f in names if f not in FORMATS]
    if unknown:
        raise ValueError(f"unknown export format {unknown[0]!r}; choose from {', '.join(FORMATS)}")
    if not names:
        raise ValueError(f"no export format given; choose from {', '.join(FORMATS)}")
    return list(dict.fromkeys(names))


def planned_files(result, out_dir: Path, formats: list[str], marks=None) -> list[Path]:
    """Every file :func:`export_result` will write (world-file sidecars included)."""
    ok = [k for k in range(result.n_frames) if result.is_ok(k)]
    return _frame_files(result, out_dir, formats, ok) + _sequence_files(
        result, out_dir, formats, marks
    )


def _frame_files(result, out_dir: Path, formats: list[str], ks: list[int], *, every=False):
    """The per-frame files of ``formats`` for frames ``ks``; ``every``: with every sidecar a
    georeference could add and a ``.points`` file whether or not the frame has points (the
    names an earlier export may have left)."""
    georef = result.georef
    crs = every or (georef is not None and georef.crs_wkt is not None)
    files: list[Path] = []
    for f in formats:
        if f in ("geotiff", "cog"):
            files += [out_dir / f / f"{k:06d}.tif" for k in ks]
        elif f == "png":
            for k in ks:
                png = out_dir / "png" / f"{k:06d}.png"
                files.append(png)
                files.append(png.with_suffix(".pgw"))
                if crs:
                    files += [png.with_suffix(".prj"), Path(str(png) + ".aux.xml")]
        elif f == "points":
            files += [
                out_dir / "points" / f"{k:06d}.points"
                for k in ks
                if every or result.control_points(k) is not None
            ]
    return files


def _sequence_files(result, out_dir: Path, formats: list[str], marks) -> list[Path]:
    """The files of ``formats`` that cover the whole sequence."""
    georef = result.georef
    crs = georef is not None and georef.crs_wkt is not None
    files: list[Path] = []
    for f in formats:
        if f in ("geotiff", "cog", "png", "points"):
            continue  # per frame: _frame_files
        if f == "mosaic":
            files.append(out_dir / "mosaic.tif")
        elif f == "mp4":
            files.append(out_dir / "registered.mp4")
            files.append(out_dir / "registered.wld")
            if crs:
                files.append(out_dir / "registered.prj")
        elif f == "transforms":
            files.append(out_dir / "transforms.json")
        elif f == "geojson":
            names = ["control_points", "footprints"] + (["marks"] if marks is not None else [])
            files += [out_dir / f"{n}.geojson" for n in names]
        elif f == "gpkg":
            files.append(out_dir / "aerialreg.gpkg")
    return files


def export_result(
    result,
    out_dir: str | os.PathLike,
    formats,
    *,
    frames=None,
    georef: GeoReference | None = None,
    marks=None,
    options: ExportOptions = ExportOptions(),
    progress: Progress | None = None,
    cancel: threading.Event | None = None,
) -> dict[str, Any]:
    """Write ``formats`` (names from :data:`FORMATS`, or ``"all"``) of a result into ``out_dir``.

    The app's export buttons call this with one format and a progress callback; the CLI's
    ``aerialreg export`` with what was asked for.

    Args:
        result: a registration result (``registration.load``).
        out_dir: output folder (created).
        formats: format names (module docstring).
        frames: frame source with ``get(k)`` (:func:`registration.io.frames.open_frames`); needed for
            the raster formats (None = open the result's ``frames_source``).
        georef: the base map's georeference when the result has none recorded (a result made
            before georeferencing was recorded) or to override it.
        marks: hand-marked points (:func:`registration.evaluation.points.read_points_csv`) for a
            ``marks`` layer in GeoJSON/GeoPackage.
        options: :class:`ExportOptions`.
        progress: called as ``progress(done, total)`` (one step per rendered frame and per
            file of the other formats).
        cancel: when set, stops after the current frame; files already written stay.

    Returns:
        ``{"out", "formats", "files": {format: [paths]}, "n_frames", "n_failed", "box",
        "time_s": {...}, "cancelled", "failed_frames", "removed_stale"}``: failed frames are
        holes (left out of every format, never read); with ``force``, what an earlier export
        wrote for frames that are failed now is removed (``removed_stale``).

    Raises:
        ValueError: unknown format or option, a format that needs a georeferenced base
            without one, files that exist without ``force``, nothing registered.
    """
    options.validate()
    formats = resolve_formats(formats)
    out = Path(out_dir)
    if georef is not None:
        result = _with_georef(result, georef)
    _check_request(result, out, formats, marks, options)
    ok = [k for k in range(result.n_frames) if result.is_ok(k)]
    raster = [f for f in formats if f in RASTER_FORMATS]
    vector = [f for f in formats if f not in RASTER_FORMATS]
    if raster:
        frames = _check_frames(result, frames)
    render_ks = _frames_to_render(ok, raster, options)
    total = len(render_ks) + len(vector) + (1 if "mosaic" in raster else 0)
    step = [0]

    def tick() -> None:
        step[0] += 1
        if progress:
            progress(step[0], total)

    if progress:
        progress(0, total)
    summary = _new_summary(out, formats, result.n_frames, len(ok))
    summary["failed_frames"] = [k for k in range(result.n_frames) if not result.is_ok(k)]
    if options.force:
        summary["removed_stale"] = _remove_stale(result, out, formats, summary["failed_frames"])
    if raster:
        _export_rasters(result, frames, out, raster, render_ks, options, summary, tick, cancel)
    if not summary["cancelled"]:
        _export_vectors(result, out, vector, marks, options, summary, tick)
    return summary


def _remove_stale(result, out: Path, formats: list[str], failed: list[int]) -> list[str]:
    """Delete what an earlier export into ``out`` wrote for frames that are failed now (a
    result registered again), and the temporary files a killed export left of any name this
    export writes: exactly those names, nothing else."""
    removed = []
    for path in _frame_files(result, out, formats, failed, every=True):
        if path.is_file() and not path.is_symlink():
            path.unlink()
            removed.append(str(path))
    every = list(range(result.n_frames))
    names: dict[Path, set[str]] = {}
    for path in _frame_files(result, out, formats, every, every=True) + _sequence_files(
        result, out, formats, marks=True
    ):
        names.setdefault(path.parent, set()).add(path.name)
    for folder, own in names.items():
        if not folder.is_dir():
            continue
        for entry in os.scandir(folder):
            if temp_target(entry.name) in own and entry.is_file(follow_symlinks=False):
                os.unlink(entry.path)
                removed.append(entry.path)
    return removed


def _with_georef(result, georef: GeoReference):
    """A shallow copy of ``result`` with ``georef`` (the caller's result keeps its own)."""
    if not isinstance(georef, GeoReference):
        raise ValueError("georef must be a registration.gis.georef.GeoReference")
    result = copy.copy(result)
    result.georef = georef
    return result


def _new_summary(out: Path, formats: list[str], n_frames: int, n_ok: int) -> dict[str, Any]:
    """:func:`export_result`'s summary before anything is written (no files, no box)."""
    return {
        "out": str(out),
        "formats": formats,
        "files": {f: [] for f in formats},
        "n_frames": n_frames,
        "n_failed": n_frames - n_ok,
        "box": None,
        "time_s": {},
        "cancelled": False,
        "failed_frames": [],
        "removed_stale": [],
    }


def _export_vectors(result, out: Path, vector: list[str], marks, options, summary, tick) -> None:
    """Write each of the ``vector`` (non-raster) formats in turn, recording its files and
    time (s) in ``summary`` and calling ``tick()`` after each."""
    for f in vector:
        t0 = time.perf_counter()
        summary["files"][f] = [str(p) for p in _export_vector(result, out, f, marks, options)]
        summary["time_s"][f] = round(time.perf_counter() - t0, 4)
        tick()


def _check_request(result, out: Path, formats: list[str], marks, options) -> None:
    """ValueError for a request that cannot be served, before anything is written."""
    folders, files = input_locations(result.meta.get("frames_source"), result.meta.get("base_path"))
    own = Path(result.out_dir)
    check_not_an_input(
        out, [*folders, own / "frames", own / "registered"], files, "the export folder"
    )
    needs_map = [f for f in formats if f in MAP_FORMATS]
    if needs_map and result.georef is None:
        raise NotGeoreferenced(
            f"format {needs_map[0]!r} needs a georeferenced base map, and this result's base "
            "is a plain image",
            out,
        )
    if not any(result.is_ok(k) for k in range(result.n_frames)):
        raise ValueError("no frame of the result is registered; nothing to export")
    files = planned_files(result, out, formats, marks)
    if not options.force:
        existing = [f for f in files if f.exists()]
        if existing:
            raise FilesExist(existing[0], len(existing), len(files))


def _check_frames(result, frames):
    """The frame source (the result's own when None), checked against the result."""
    if frames is None:
        from registration.io import open_frames

        frames = open_frames(result.meta["frames_source"])
    check_result_frames(frames, result)
    return frames


def _frames_to_render(ok: list[int], raster: list[str], options: ExportOptions) -> list[int]:
    if not raster:
        return []
    if set(raster) - {"mosaic"} or options.mosaic == "mean":
        return list(ok)
    return _spread(ok, options.mosaic_frames)


def _spread(ks: list[int], count: int) -> list[int]:
    """Up to ``count`` of ``ks`` spread evenly (first and last included)."""
    if len(ks) <= count:
        return list(ks)
    idx = np.unique(np.round(np.linspace(0, len(ks) - 1, count)).astype(int))
    return [ks[i] for i in idx]


def _export_vector(result, out: Path, fmt: str, marks, options: ExportOptions) -> list[Path]:
    georef = result.georef
    stage = options.stage
    if fmt == "transforms":
        doc = transforms_document(result, georef, stage)
        path = out / "transforms.json"
        write_json_atomic(path, doc)
        return [path]
    if fmt == "points":
        return write_points_files(result, out / "points", georef or PIXEL_GRID)
    vcrs = options.vector_crs
    crs_wkt = parse_crs(vcrs).to_wkt() if vcrs is not None else georef.crs_wkt
    layers = [
        control_point_layer(result, georef, vcrs),
        footprint_layer(result, georef, stage, vcrs),
    ]
    if marks is not None:
        layers.append(marks_layer(result, georef, marks, stage, vcrs))
    if fmt == "geojson":
        return [write_geojson(out / f"{lay.name}.geojson", lay, crs_wkt) for lay in layers]
    return [write_geopackage(out / "aerialreg.gpkg", layers, crs_wkt)]


class _Cancelled(Exception):
    pass


def _export_rasters(result, frames, out, raster, render_ks, options, summary, tick, cancel):
    """Render the frames once (each in its own footprint box) and feed every raster format."""
    from registration.render import footprint, write_video

    # A plain base's own pixel grid places the frames' PNGs and the video on the base image.
    georef = result.georef if result.georef is not None else PIXEL_GRID
    stage = options.stage
    fsize, bsize = tuple(result.frame_size), tuple(result.base_size)
    ok = [k for k in range(result.n_frames) if result.is_ok(k)]
    seq = footprint(
        [lambda q, k=k: result.frame_to_base(k, q, stage) for k in ok], fsize, bsize, pad=2
    )
    if seq[2] == 0 or seq[3] == 0:
        raise ValueError("no registered frame maps into the base map; nothing to render")
    summary["box"] = list(seq)
    times = summary["time_s"]
    for f in ("render", *raster):
        times[f] = 0.0
    mosaic_ks = set(_spread(ok, options.mosaic_frames) if options.mosaic == "median" else ok)
    mosaic = _Mosaic(seq, options.mosaic, len(mosaic_ks)) if "mosaic" in raster else None
    todo = set(render_ks)
    files = summary["files"]
    video = "mp4" in raster

    def frame_images() -> Iterator[NDArray]:
        for k, frame in _frames_in_order(frames, result.n_frames, todo):
            if cancel is not None and cancel.is_set():
                raise _Cancelled
            canvas = np.zeros((seq[3], seq[2], 3), np.uint8) if video else None
            if frame is not None:
                t0 = time.perf_counter()
                img, mask, box = _render_frame(result, frame, k, stage, bsize, options.step)
                times["render"] += time.perf_counter() - t0
                if img is not None:
                    if video:
                        _paste(canvas, img, box, seq)
                    for f in ("geotiff", "cog", "png"):
                        if f in raster:
                            t0 = time.perf_counter()
                            files[f] += _write_frame(
                                out, f, k, img, mask, box, seq, georef, options
                            )
                            times[f] += time.perf_counter() - t0
                    if mosaic is not None and k in mosaic_ks:
                        t0 = time.perf_counter()
                        mosaic.add(img, mask, box)
                        times["mosaic"] += time.perf_counter() - t0
                tick()
            yield canvas

    try:
        if video:
            t0 = time.perf_counter()
            files["mp4"] = _write_video(out, frame_images(), seq, georef, options, write_video)
            times["mp4"] += (
                time.perf_counter()
                - t0
                - sum(times[f] for f in ("render", "geotiff", "cog", "png", "mosaic") if f in times)
            )
        else:
            for _ in frame_images():
                pass
    except _Cancelled:
        summary["cancelled"] = True
        return
    if mosaic is not None:
        t0 = time.perf_counter()
        image, mask = mosaic.result()
        path = out / "mosaic.tif"
        gr = georef.cropped(seq[0], seq[1])
        write_geotiff(path, image, gr, mask=mask, cog=True, compress=options.compress)
        files["mosaic"] = [str(path)]
        times["mosaic"] += time.perf_counter() - t0
        tick()
    for f in times:
        times[f] = round(times[f], 4)


def _frames_in_order(frames, n: int, todo: set[int]) -> Iterator[tuple[int, NDArray | None]]:
    """``(k, frame)`` for k = 0..n-1, the frame None when not in ``todo``; frames not in
    ``todo`` (failed ones among them, which may be unreadable) are never read. A video is
    decoded sequentially (seeking per frame is slow) unless only a few frames are needed; from
    a stretch it cannot decode on, frame by frame."""
    start = 0
    if getattr(frames, "video_path", None) is not None and 4 * len(todo) >= n:
        try:
            for k, frame in frames.iter(0):
                start = k + 1
                yield k, (frame if k in todo else None)
        except (ValueError, OSError):
            pass  # a damaged stretch of the video: the frames after it one by one
    for k in range(start, n):
        yield k, (frames.get(k) if k in todo else None)


def _render_frame(result, frame, k, stage, base_size, step):
    """Frame ``k`` rendered into its own footprint box of base pixels: ``(image, mask, box)``
    with ``box = (x0, y0, w, h)``; ``(None, None, None)`` when it maps outside the base."""
    from registration.render import footprint, render_registered

    box = footprint(
        [lambda q: result.frame_to_base(k, q, stage)], tuple(result.frame_size), base_size, pad=2
    )
    if box[2] == 0 or box[3] == 0:
        return None, None, None
    img, mask = render_registered(
        frame,
        lambda b: result.base_to_frame(k, b, stage),
        (box[2], box[3]),
        (box[0], box[1]),
        step=step,
        return_mask=True,
    )
    # The outermost pixels interpolate between the frame's edge and the black outside it:
    # leave them out so that mosaics and overlays show no dark seams.
    mask = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    img[~mask] = 0
    return img, mask, box


def _paste(canvas: NDArray, img: NDArray, box, seq) -> None:
    x, y = box[0] - seq[0], box[1] - seq[1]
    h, w = img.shape[:2]
    canvas[y : y + h, x : x + w] = img


def _write_frame(out, fmt, k, img, mask, box, seq, georef, options) -> list[str]:
    if options.crop == "sequence":
        full = np.zeros((seq[3], seq[2], 3), np.uint8)
        full_mask = np.zeros((seq[3], seq[2]), bool)
        _paste(full, img, box, seq)
        x, y = box[0] - seq[0], box[1] - seq[1]
        full_mask[y : y + mask.shape[0], x : x + mask.shape[1]] = mask
        img, mask, box = full, full_mask, seq
    gr = None if georef is None else georef.cropped(box[0], box[1])
    if fmt == "png":
        paths = write_png_georeferenced(out / "png" / f"{k:06d}.png", img, gr, mask=mask)
        return [str(p) for p in paths]
    path = out / fmt / f"{k:06d}.tif"
    write_geotiff(path, img, gr, mask=mask, cog=fmt == "cog", compress=options.compress)
    return [str(path)]


def _write_video(out, images, seq, georef, options, write_video) -> list[str]:
    s = options.video_scale
    w, h = seq[2], seq[3]
    size = (max(2, int(round(w * s))), max(2, int(round(h * s))))
    if size != (w, h):
        images = (cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in images)
    path = write_video(images, out / "registered.mp4", fps=options.fps)
    written = [str(path)]
    if georef is not None:
        gr = georef.cropped(seq[0], seq[1]).scaled(size[0] / w, size[1] / h)
        written += [str(p) for p in write_world_files(path, gr, world_suffix=".wld", aux=False)]
    return written


class _Mosaic:
    """Per-pixel median (of the frames added) or mean of registered frames over the sequence
    box ``(x0, y0, w, h)``; a median keeps the frame crops and combines them in row strips."""

    STRIP = 256

    def __init__(self, seq, method: str, max_frames: int = 65535) -> None:
        self.seq, self.method = seq, method
        w, h = seq[2], seq[3]
        self.crops: list[tuple[NDArray, NDArray, tuple]] = []
        if method == "mean":
            # The narrowest integer sums that cannot overflow: exact, and cheap to add.
            self.total = np.zeros((h, w, 3), np.uint16 if max_frames <= 257 else np.uint32)
            self.count = np.zeros((h, w), np.uint16 if max_frames <= 65535 else np.uint32)

    def add(self, img: NDArray, mask: NDArray, box) -> None:
        if self.method == "median":
            self.crops.append((img, mask, box))
            return
        x, y = box[0] - self.seq[0], box[1] - self.seq[1]
        hh, ww = mask.shape
        self.total[y : y + hh, x : x + ww] += img * mask[..., None]
        self.count[y : y + hh, x : x + ww] += mask

    def result(self) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        if self.method == "mean":
            n = np.maximum(self.count, 1).astype(np.float32)[..., None]
            image = (self.total.astype(np.float32) / n + 0.5).astype(np.uint8)
            return image, self.count > 0
        w, h = self.seq[2], self.seq[3]
        image = np.zeros((h, w, 3), np.uint8)
        valid = np.zeros((h, w), bool)
        for y0 in range(0, h, self.STRIP):
            y1 = min(h, y0 + self.STRIP)
            image[y0:y1], valid[y0:y1] = self._median_strip(y0, y1, w)
        return image, valid

    def _median_strip(self, y0: int, y1: int, w: int):
        sx, sy = self.seq[0], self.seq[1]
        rows = [c for c in self.crops if c[2][1] - sy < y1 and c[2][1] - sy + c[2][3] > y0]
        # Missing data sorts last (512 > any uint8), so the first ``count`` values are real.
        vals = np.full((max(len(rows), 1), y1 - y0, w, 3), 512, np.uint16)
        for i, (img, mask, box) in enumerate(rows):
            x, y = box[0] - sx, box[1] - sy
            a, b = max(y0, y), min(y1, y + box[3])
            sub, sub_mask = img[a - y : b - y], mask[a - y : b - y]
            dst = vals[i, a - y0 : b - y0, x : x + box[2]]
            np.copyto(dst, sub, where=sub_mask[..., None])
        _sort_planes(vals)
        count = (vals[..., 0] < 512).sum(axis=0)
        lo = np.maximum(count - 1, 0) // 2
        hi = np.minimum(count // 2, np.maximum(count - 1, 0))
        # The two middle values (equal for an odd count), picked plane by plane.
        med = np.zeros((y1 - y0, w, 3), np.uint16)
        for j in range(len(vals)):
            np.add(med, vals[j], out=med, where=(lo == j)[..., None])
            np.add(med, vals[j], out=med, where=(hi == j)[..., None])
        med = (med + 1) // 2
        med[count == 0] = 0
        return med.astype(np.uint8), count > 0


def _sort_planes(vals: NDArray) -> None:
    """Sort ``vals`` along axis 0 in place with an odd-even transposition network: element-wise
    min/max of whole planes, much faster than ``np.sort(axis=0)``'s many tiny sorts when the
    axis is short (a few to a few tens of frames)."""
    n = len(vals)
    tmp = np.empty_like(vals[0])
    for r in range(n):
        for i in range(r % 2, n - 1, 2):
            a, b = vals[i], vals[i + 1]
            np.minimum(a, b, out=tmp)
            np.maximum(a, b, out=b)
            a[...] = tmp
