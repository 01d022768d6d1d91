"""Vector GIS files of a registration result, in map coordinates: QGIS georeferencer
``.points`` files, GeoJSON and GeoPackage (written without GDAL: JSON and SQLite), and the
layers they hold (control points, frame footprints, hand-marked ground points)."""

from __future__ import annotations

import json
import math
import os
import sqlite3
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.coords import frame_outline
from registration.gis.georef import GeoReference, parse_crs
from registration.io import atomic_path, write_bytes_atomic

QGIS_POINTS_HEADER = "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"
# Where an intra-sensor frame's control point was matched (``source`` of the fine step).
MATCHED_IN = {0: "mid base", 1: "previous frame"}


def write_points_file(
    path: str | os.PathLike,
    source_xy: NDArray,
    map_xy: NDArray,
    *,
    crs_wkt: str | None,
    enabled: NDArray[np.bool_] | None = None,
    residual_xy: NDArray | None = None,
) -> Path:
    """Control points as a QGIS georeferencer ``.points`` file (the format QGIS 3 saves).

    Layout: ``#CRS: <WKT>`` (when known), then ``mapX,mapY,sourceX,sourceY,enable,dX,dY,residual``
    and one line per point. QGIS's source coordinates put the **corner** of the image's top-left
    pixel at (0, 0) with y growing *upwards*, so rows are negative: a point at pixel-centre
    coordinates ``(x, y)`` (this project's convention) is written ``sourceX = x + 0.5``,
    ``sourceY = -(y + 0.5)``.

    Args:
        source_xy: ``(N, 2)`` pixel coordinates in the source image (here: raw frame px).
        map_xy: ``(N, 2)`` map coordinates in ``crs_wkt``.
        enabled: ``(N,)`` bool, the ``enable`` column (default all 1).
        residual_xy: ``(N, 2)`` residuals for ``dX``, ``dY`` (``residual`` = their length);
            QGIS ignores these columns on loading and computes its own.
    """
    src = np.asarray(source_xy, float).reshape(-1, 2)
    dst = np.asarray(map_xy, float).reshape(-1, 2)
    n = len(src)
    en = np.ones(n, bool) if enabled is None else np.asarray(enabled, bool)
    res = np.zeros((n, 2)) if residual_xy is None else np.nan_to_num(np.asarray(residual_xy))
    lines = [f"#CRS: {crs_wkt}"] if crs_wkt else []
    lines.append(QGIS_POINTS_HEADER)
    for (mx, my), (sx, sy), e, (dx, dy) in zip(dst, src, en, res, strict=True):
        values = (mx, my, sx + 0.5, -(sy + 0.5), int(e), dx, dy, math.hypot(dx, dy))
        lines.append(",".join(repr(v) if isinstance(v, int) else repr(float(v)) for v in values))
    path = Path(path)
    write_bytes_atomic(path, ("\n".join(lines) + "\n").encode())
    return path


def read_points_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read a QGIS ``.points`` file as QGIS does: optional ``#CRS:`` line, a header, then
    comma- (or tab-) separated rows of at least ``mapX, mapY, sourceX, sourceY``.

    Returns:
        ``{"crs": str | None, "map": (N, 2), "source": (N, 2) pixel-centre coordinates
        (QGIS's corner/y-up coordinates converted back), "enable": (N,) bool}``.

    Raises:
        ValueError: naming the line of malformed content.
    """
    p = Path(path)
    lines = p.read_text(encoding="utf-8-sig").splitlines()
    crs = None
    if lines and lines[0].startswith("#CRS: "):
        crs = lines.pop(0)[len("#CRS: ") :]
        first = 2
    else:
        first = 1
    if not lines or not lines[0].lower().startswith("mapx,mapy,"):
        raise ValueError(f"{p.name}: missing the header line '{QGIS_POINTS_HEADER}'")
    rows = []
    for i, line in enumerate(lines[1:], start=first + 1):
        if not line.strip():
            continue
        fields = line.split(",") if "," in line else line.split("\t")
        try:
            values = [float(v) for v in fields[:4]]
            enable = bool(int(fields[4])) if len(fields) >= 5 else True
        except ValueError:
            values = []
        if len(values) < 4:
            raise ValueError(f"{p.name} line {i}: malformed content {line!r}")
        rows.append((*values, enable))
    arr = np.array([r[:4] for r in rows], float).reshape(-1, 4)
    return {
        "crs": crs,
        "map": arr[:, :2],
        "source": np.c_[arr[:, 2] - 0.5, -arr[:, 3] - 0.5],
        "enable": np.array([r[4] for r in rows], bool),
    }


# --------------------------------------------------------------------------------------------
# Vector data: features in map coordinates


@dataclass
class Layer:
    """Features of one geometry type: ``geometries`` are ``(2,)`` points, ``(M, 2)`` line
    strings or ``(M, 2)`` closed polygon rings in map coordinates; ``properties`` one dict per
    feature."""

    name: str
    geometry_type: str  # "Point", "LineString" or "Polygon"
    geometries: list[NDArray]
    properties: list[dict[str, Any]]


def _geojson_crs_member(crs) -> dict | None:
    epsg = crs.to_epsg() if crs is not None else None
    if epsg is None:
        return None
    return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{epsg}"}}


def write_geojson(path: str | os.PathLike, layer: Layer, crs_wkt: str | None) -> Path:
    """One layer as a GeoJSON FeatureCollection. In WGS 84 (EPSG:4326) coordinates are
    (longitude, latitude) as RFC 7946 requires and no ``crs`` member is written; in any other
    CRS with an EPSG code, the ``crs`` member GDAL and QGIS read (GeoJSON 2008) names it."""
    crs = parse_crs(crs_wkt) if crs_wkt else None
    features = []
    for geom, props in zip(layer.geometries, layer.properties, strict=True):
        g = np.asarray(geom, float)
        if layer.geometry_type == "Point":
            geometry = {"type": "Point", "coordinates": [float(g[0]), float(g[1])]}
        elif layer.geometry_type == "LineString":
            geometry = {"type": "LineString", "coordinates": g.tolist()}
        else:
            geometry = {"type": "Polygon", "coordinates": [g.tolist()]}
        features.append({"type": "Feature", "geometry": geometry, "properties": props})
    doc: dict[str, Any] = {"type": "FeatureCollection", "name": layer.name}
    if crs is not None and crs.to_epsg() != 4326:
        member = _geojson_crs_member(crs)
        if member:
            doc["crs"] = member
    doc["features"] = features
    path = Path(path)
    write_bytes_atomic(path, json.dumps(doc, indent=None, allow_nan=False).encode() + b"\n")
    return path


def _wkb(geometry_type: str, g: NDArray) -> bytes:
    if geometry_type == "Point":
        return struct.pack("<BI2d", 1, 1, float(g[0]), float(g[1]))
    coords = np.ascontiguousarray(g, "<f8")
    if geometry_type == "LineString":
        return struct.pack("<BII", 1, 2, len(coords)) + coords.tobytes()
    return struct.pack("<BIII", 1, 3, 1, len(coords)) + coords.tobytes()


def _gpkg_blob(geometry_type: str, g: NDArray, srs_id: int) -> bytes:
    """GeoPackage geometry: 'GP', version 0, flags (little endian; envelope [minx, maxx,
    miny, maxy] for polygons and lines), srs_id, then standard WKB."""
    g = np.asarray(g, float)
    if geometry_type == "Point":
        return b"GP" + struct.pack("<BBi", 0, 0b01, srs_id) + _wkb(geometry_type, g)
    env = struct.pack("<4d", g[:, 0].min(), g[:, 0].max(), g[:, 1].min(), g[:, 1].max())
    return b"GP" + struct.pack("<BBi", 0, 0b11, srs_id) + env + _wkb(geometry_type, g)


_SQL_TYPES = {bool: "BOOLEAN", int: "INTEGER", float: "DOUBLE", str: "TEXT"}


def write_geopackage(path: str | os.PathLike, layers: list[Layer], crs_wkt: str | None) -> Path:
    """Layers as one OGC GeoPackage (1.3; SQLite, written without GDAL), atomically.

    The CRS goes into ``gpkg_spatial_ref_sys`` under its EPSG code, or as a custom entry
    (srs_id 100000) when it has none; without a CRS the layers use the spec's "undefined
    Cartesian" (-1).
    """
    from pyproj.enums import WktVersion

    path = Path(path)
    crs = parse_crs(crs_wkt) if crs_wkt else None
    epsg = crs.to_epsg() if crs is not None else None
    srs_id = -1 if crs is None else (epsg if epsg is not None else 100000)
    with atomic_path(path) as tmp:
        tmp.unlink()  # SQLite makes the database file itself
        con = sqlite3.connect(tmp)
        try:
            _gpkg_schema(con)
            if crs is not None and srs_id != 4326:
                con.execute(
                    "INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)",
                    (
                        crs.name,
                        srs_id,
                        "EPSG" if epsg is not None else "NONE",
                        epsg if epsg is not None else srs_id,
                        crs.to_wkt(WktVersion.WKT1_GDAL),
                        "",
                    ),
                )
            for layer in layers:
                _gpkg_layer(con, layer, srs_id)
            con.commit()
        finally:
            con.close()
    return path


def _gpkg_schema(con: sqlite3.Connection) -> None:
    con.execute("PRAGMA application_id = 1196444487")  # 'GPKG'
    con.execute("PRAGMA user_version = 10300")
    con.executescript(
        """
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY,
          organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL,
          definition TEXT NOT NULL, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY,
          data_type TEXT NOT NULL, identifier TEXT UNIQUE, description TEXT DEFAULT '',
          last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
          min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
          CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
        CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
          geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL,
          m TINYINT NOT NULL, CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
          CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
          CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
        INSERT INTO gpkg_spatial_ref_sys VALUES ('Undefined cartesian SRS', -1, 'NONE', -1,
          'undefined', 'undefined cartesian coordinate reference system');
        INSERT INTO gpkg_spatial_ref_sys VALUES ('Undefined geographic SRS', 0, 'NONE', 0,
          'undefined', 'undefined geographic coordinate reference system');
        """
    )
    from pyproj import CRS
    from pyproj.enums import WktVersion

    con.execute(
        "INSERT INTO gpkg_spatial_ref_sys VALUES ('WGS 84 geodetic', 4326, 'EPSG', 4326, ?, ?)",
        (CRS.from_epsg(4326).to_wkt(WktVersion.WKT1_GDAL), "longitude/latitude, WGS 84"),
    )


def _gpkg_layer(con: sqlite3.Connection, layer: Layer, srs_id: int) -> None:
    columns: dict[str, str] = {}
    for props in layer.properties:
        for k, v in props.items():
            if v is not None and k not in columns:
                columns[k] = _SQL_TYPES.get(type(v), "TEXT")
    name = layer.name
    cols = "".join(f', "{k}" {t}' for k, t in columns.items())
    geom = layer.geometry_type.upper()
    con.execute(
        f'CREATE TABLE "{name}" (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom {geom}{cols})'
    )
    placeholders = ", ".join("?" * (len(columns) + 1))
    names = ", ".join(["geom", *(f'"{k}"' for k in columns)])
    for g, props in zip(layer.geometries, layer.properties, strict=True):
        row = [_gpkg_blob(layer.geometry_type, g, srs_id)]
        row += [_sql_value(props.get(k)) for k in columns]
        con.execute(f'INSERT INTO "{name}" ({names}) VALUES ({placeholders})', row)
    pts = (
        np.concatenate([np.asarray(g, float).reshape(-1, 2) for g in layer.geometries])
        if layer.geometries
        else np.zeros((0, 2))
    )
    bbox = [None] * 4 if not len(pts) else [*pts.min(axis=0), *pts.max(axis=0)]
    con.execute(
        "INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, "
        "max_y, srs_id) VALUES (?, 'features', ?, ?, ?, ?, ?, ?)",
        (name, name, *(None if v is None else float(v) for v in bbox), srs_id),
    )
    con.execute(
        "INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, ?, 0, 0)", (name, geom, srs_id)
    )


def _sql_value(v):
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (dict, list)):
        return json.dumps(v)
    return v


def _to_vector_crs(georef: GeoReference, map_xy: NDArray, vector_crs) -> NDArray:
    return map_xy if vector_crs is None else georef.to_crs(map_xy, vector_crs)


def control_point_layer(result, georef: GeoReference, vector_crs=None) -> Layer:
    """Every frame's control points at their base-map position (``dst``) in map coordinates,
    with the raw-frame pixel they came from, whether REQCON kept them and their residual."""
    geoms, props = [], []
    ref = result.reference_frame
    for k in range(result.n_frames):
        cps = result.control_points(k) if result.is_ok(k) else None
        if cps is None:
            continue
        src, dst, kept, residuals = cps
        source = result._npz(k).get("source")  # where each point matched (no public accessor)
        raw = result.lens.raw_from_corrected(src)
        xy = _to_vector_crs(georef, georef.map_from_base(dst), vector_crs)
        for i in np.flatnonzero(np.isfinite(xy).all(axis=1) & np.isfinite(raw).all(axis=1)):
            geoms.append(xy[i])
            kind = (
                "base map"
                if k == ref
                else MATCHED_IN.get(int(source[i]) if source is not None else 0, "mid base")
            )
            props.append(
                {
                    "frame": int(k),
                    "matched_in": kind,
                    "source_x": float(raw[i, 0]),
                    "source_y": float(raw[i, 1]),
                    "base_x": float(dst[i, 0]),
                    "base_y": float(dst[i, 1]),
                    "kept": bool(kept[i]),
                    "residual_px": float(residuals[i]) if np.isfinite(residuals[i]) else None,
                }
            )
    return Layer("control_points", "Point", geoms, props)


def footprint_layer(result, georef: GeoReference, stage: str, vector_crs=None) -> Layer:
    """Each registered frame's outline (its raw border through ``frame_to_map``) as a polygon."""
    outline = frame_outline(*result.frame_size, per_edge=16)
    geoms, props = [], []
    for k in range(result.n_frames):
        if not result.is_ok(k):
            continue
        ring = _to_vector_crs(georef, result.frame_to_map(k, outline, stage), vector_crs)
        if not np.isfinite(ring).all():
            ring = _to_vector_crs(georef, result.frame_to_map(k, outline, "global"), vector_crs)
        if not np.isfinite(ring).all():
            continue
        ring = np.vstack([ring, ring[:1]])
        area = 0.5 * abs(np.dot(ring[:-1, 0], ring[1:, 1]) - np.dot(ring[1:, 0], ring[:-1, 1]))
        geoms.append(ring)
        props.append(
            {
                "frame": int(k),
                "stage": stage,
                "reference": bool(k == result.reference_frame),
                "area": float(area),
            }
        )
    return Layer("footprints", "Polygon", geoms, props)


def marks_layer(result, georef: GeoReference, marks, stage: str, vector_crs=None) -> Layer:
    """Hand-marked ground points (:class:`registration.evaluation.points.PointMarks`) at their
    registered map position in every marked frame, plus each point's mean position with the
    RMS distance of its marks from it (``spread``, in map units: the registration's jitter there).
    """
    geoms, props = [], []
    for point in marks.order:
        by_frame = marks.marks[point]
        frames = sorted(by_frame)
        raw = np.array([by_frame[k] for k in frames], float)
        pos = np.vstack(
            [result.frame_to_map(k, raw[i : i + 1], stage) for i, k in enumerate(frames)]
        )
        ok = np.isfinite(pos).all(axis=1)
        out = _to_vector_crs(georef, pos, vector_crs)
        for i in np.flatnonzero(ok):
            geoms.append(out[i])
            props.append(
                {
                    "point": point,
                    "frame": int(frames[i]),
                    "kind": "mark",
                    "stage": stage,
                    "raw_x": float(raw[i, 0]),
                    "raw_y": float(raw[i, 1]),
                    "spread": None,
                }
            )
        if ok.sum() >= 1:
            mean = pos[ok].mean(axis=0)
            spread = float(np.sqrt(np.mean(np.sum((pos[ok] - mean) ** 2, axis=1))))
            geoms.append(_to_vector_crs(georef, mean[None], vector_crs)[0])
            props.append(
                {
                    "point": point,
                    "frame": None,
                    "kind": "mean",
                    "stage": stage,
                    "raw_x": None,
                    "raw_y": None,
                    "spread": spread,
                    "n_frames": int(ok.sum()),
                }
            )
    return Layer("marks", "Point", geoms, props)


def write_points_files(result, folder: Path, georef: GeoReference) -> list[Path]:
    """One ``.points`` file per registered frame: its control points, source = raw frame px,
    map = where they matched in the base map (or mid base / previous frame, all base px)."""
    written = []
    for k in range(result.n_frames):
        cps = result.control_points(k) if result.is_ok(k) else None
        if cps is None:
            continue
        src, dst, kept, _ = cps
        raw = result.lens.raw_from_corrected(src)
        model = result.model(k)
        fit_map = georef.map_from_base(model.apply(src))
        dst_map = georef.map_from_base(dst)
        ok = np.isfinite(raw).all(axis=1) & np.isfinite(dst_map).all(axis=1)
        written.append(
            write_points_file(
                folder / f"{k:06d}.points",
                raw[ok],
                dst_map[ok],
                crs_wkt=georef.crs_wkt,
                enabled=kept[ok],
                residual_xy=(fit_map - dst_map)[ok],
            )
        )
    return written
