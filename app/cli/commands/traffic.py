"""``aerialreg traffic``: vehicles, tracks, speeds and the velocity field of a registered
sequence."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from app.cli.common import emit_json
from app.progress import LazyProgressBar

NAME = "traffic"
HELP = (
    "Track the vehicles on a registered sequence: inD-style tracks.csv / tracksMeta.csv / "
    "recordingMeta.csv, latitude/longitude CSV, GeoJSON and GeoPackage trajectories and a "
    "velocity-field GeoTIFF (resumable)."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("result", metavar="RESULT", help="folder written by 'aerialreg register'")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (resumes there)")
    p.add_argument(
        "--frames", help="the registered video / image folder / glob (default: RESULT's own)"
    )
    p.add_argument(
        "--fps",
        type=float,
        help="frame rate, frames/s (needed for image folders; a video's timestamps otherwise)",
    )
    p.add_argument(
        "--gsd",
        type=float,
        metavar="M",
        help="metres per base-map pixel (needed when the base has no projected CRS in metres)",
    )
    p.add_argument(
        "--exclude",
        metavar="REGIONS.geojson",
        help="polygons never to look for vehicles in (map coordinates of a georeferenced base, "
        "else base pixels)",
    )
    p.add_argument(
        "--sections",
        metavar="SECTIONS.geojson",
        help="lines drawn across roads (LineStrings from their first to their last point, map "
        "coordinates of a georeferenced base, else base pixels; named by a 'name' property): "
        "counts.csv and crossings.csv say how many vehicles crossed each, in each direction",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object with the summary")


def _geometries(path: str, option: str) -> list[tuple[dict, dict]]:
    """``(geometry, properties)`` of each feature of the GeoJSON file ``path`` given with
    ``option`` (a FeatureCollection, a Feature or a bare geometry; one-line errors)."""
    from registration.io import read_text_file

    try:
        doc = json.loads(read_text_file(path, f"{option} file"))
    except ValueError as exc:
        raise ValueError(f"{option} {path} is not valid JSON ({exc})") from None
    feats = doc.get("features", [doc]) if isinstance(doc, dict) else []
    out = []
    for f in feats:
        g = f.get("geometry", f) if isinstance(f, dict) else None
        if isinstance(g, dict):
            out.append((g, f.get("properties") or {}))
    return out


def read_regions(path: str, result):
    """A base-sized bool mask of the GeoJSON polygons in ``path`` (one-line errors)."""
    import cv2
    import numpy as np

    rings = []
    for g, _ in _geometries(path, "--exclude"):
        if g.get("type") not in ("Polygon", "MultiPolygon"):
            continue
        polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
        rings += [np.asarray(p[0], float) for p in polys]
    if not rings:
        raise ValueError(f"--exclude {path} holds no Polygon or MultiPolygon")
    mask = np.zeros(result.base_size[::-1], np.uint8)
    for r in rings:
        b = result.georef.base_from_map(r) if result.georef is not None else r
        cv2.fillPoly(mask, [np.round(b).astype(np.int32)], 1)
    return mask.astype(bool)


def read_sections(path: str, result) -> list[tuple[str, tuple, tuple]]:
    """``(name, a, b)`` per GeoJSON LineString in ``path``, its ends in base px (one-line
    errors)."""
    import numpy as np

    out = []
    for g, props in _geometries(path, "--sections"):
        if g.get("type") != "LineString":
            continue
        line = np.asarray(g.get("coordinates"), float)
        if line.ndim != 2 or len(line) < 2 or line.shape[1] < 2:
            raise ValueError(f"--sections {path}: a LineString needs two points or more")
        ends = line[[0, -1], :2]
        if result.georef is not None:
            ends = result.georef.base_from_map(ends)
        name = str(props.get("name") or f"S{len(out) + 1}")
        out.append((name, tuple(ends[0]), tuple(ends[1])))
    if not out:
        raise ValueError(f"--sections {path} holds no LineString")
    return out


def run(args: argparse.Namespace) -> int:
    import registration
    from registration.io import check_result_frames, open_frames
    from registration.traffic import run_traffic

    result = registration.load(args.result)
    frames = open_frames(args.frames or result.meta["frames_source"])
    check_result_frames(frames, result)
    exclude = read_regions(args.exclude, result) if args.exclude else None
    sections = read_sections(args.sections, result) if args.sections else None
    progress = LazyProgressBar("traffic")
    t0 = time.perf_counter()
    try:
        summary = run_traffic(
            result,
            frames,
            args.out,
            fps=args.fps,
            gsd_m=args.gsd,
            exclude=exclude,
            progress=progress,
        )
    finally:
        progress.close()
    if sections and not summary.get("cancelled"):
        summary["sections"] = section_summary(args.out, result, args.gsd, sections)
    summary["total_s"] = round(time.perf_counter() - t0, 3)
    if args.json:
        emit_json(summary)
        return 0
    skipped = len(summary["skipped"])
    sys.stdout.write(
        f"{summary['n_tracks']} tracks from {summary['n_detections']} detections in "
        f"{summary['n_used']} frames ({skipped} skipped) into {args.out} in "
        f"{summary['total_s']:.1f} s\n"
    )
    for sec in summary.get("sections", []):
        parts = [
            f"{d['count']} towards {d['heading']} at {d['mean_speed_mps']:.1f} m/s"
            for d in sec["directions"]
            if d["count"]
        ]
        sys.stdout.write(f"  section {sec['name']}: {'; '.join(parts) or 'no vehicle crossed'}\n")
    return 0


def section_summary(out: str, result, gsd: float | None, sections) -> list[dict]:
    """Count the run's tracks across ``sections`` (``counts.csv``, ``crossings.csv`` in
    ``out``); per section and direction: count, heading, mean speed."""
    from registration.traffic import MetricFrame, count_sections, read_tracks_csv, write_counts_csvs

    tracks = read_tracks_csv(Path(out) / "tracks.csv")
    counted = count_sections(tracks, MetricFrame.for_result(result.georef, gsd), sections)
    write_counts_csvs(Path(out), counted)
    out = []
    for sec in counted:
        directions = []
        for d in (1, 2):
            n, speed, heading = sec.direction(d)
            directions.append(
                {
                    "direction": d,
                    "count": n,
                    "heading": heading,
                    "mean_speed_mps": speed if n else None,
                }
            )
        out.append({"name": sec.name, "directions": directions})
    return out
