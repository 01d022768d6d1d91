"""``aerialreg export``: GIS files from a registration result with a georeferenced base map."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from app.cli.common import emit_json
from app.progress import LazyProgressBar

NAME = "export"
HELP = (
    "Export a registration result for GIS: registered frames and a mosaic as GeoTIFF/COG, PNG "
    "with world files, the registered video, QGIS .points, transforms JSON, GeoJSON/GeoPackage."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from registration.gis import COMPRESSIONS, FORMATS

    p.add_argument("out", metavar="OUT", help="result folder written by 'aerialreg register'")
    p.add_argument(
        "--format",
        dest="formats",
        action="append",
        required=True,
        metavar="FMT",
        help="what to write (repeat, or comma-separated; 'all' = everything): "
        + "; ".join(f"{k}: {v}" for k, v in FORMATS.items()),
    )
    p.add_argument("--to", metavar="DIR", help="output folder (default OUT/export)")
    p.add_argument(
        "--frames",
        help="the registered video / image folder / glob (default: the one recorded in OUT)",
    )
    p.add_argument(
        "--stage",
        choices=("local", "global"),
        default="local",
        help="mapping used: global model + local field (default) or the global model only",
    )
    p.add_argument(
        "--crop",
        choices=("frame", "sequence"),
        default="frame",
        help="registered frames cropped to their own footprint (default) or all to the "
        "sequence's (one grid for all frames)",
    )
    p.add_argument(
        "--compress", choices=COMPRESSIONS, default="deflate", help="GeoTIFF compression"
    )
    p.add_argument(
        "--mosaic",
        choices=("median", "mean"),
        default="median",
        help="mosaic per pixel: median of --mosaic-frames frames spread over the sequence "
        "(moving vehicles vanish; default) or mean of all frames",
    )
    p.add_argument(
        "--mosaic-frames", type=int, default=15, help="frames in a median mosaic (default 15)"
    )
    p.add_argument("--fps", type=float, default=5.0, help="video frame rate (default 5)")
    p.add_argument(
        "--video-scale", type=float, default=1.0, help="resize factor of the video (default 1)"
    )
    p.add_argument(
        "--vector-crs",
        metavar="CRS",
        help="CRS of GeoJSON/GeoPackage coordinates (default: the base map's; EPSG:4326 gives "
        "RFC 7946 longitude/latitude)",
    )
    p.add_argument(
        "--georef",
        metavar="FILE",
        help="take the base map's georeference from FILE (a GeoTIFF, or an image with a world "
        "file) when the result has none recorded; it must have the base map's size",
    )
    p.add_argument(
        "--georef-crs", metavar="CRS", help="CRS of --georef when its files do not say it"
    )
    p.add_argument(
        "--marks",
        metavar="POINTS.csv",
        help="hand-marked ground points (point,frame,x,y as for 'aerialreg evaluate') to add as "
        "a 'marks' layer to geojson/gpkg",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing files")
    p.add_argument("--json", action="store_true", help="print one JSON object with the summary")


def run(args: argparse.Namespace) -> int:
    import registration
    from registration.gis import ExportOptions, export_result, read_georeference, resolve_formats
    from registration.gis.export import MAP_FORMATS
    from registration.io import open_frames

    formats = resolve_formats([f for spec in args.formats for f in spec.split(",") if f.strip()])
    result = registration.load(args.out)
    georef = None
    if args.georef:
        georef, size = read_georeference(args.georef, crs=args.georef_crs)
        if georef is None:
            raise ValueError(f"--georef {args.georef} holds no georeference")
        if tuple(size) != tuple(result.base_size):
            raise ValueError(
                f"--georef {args.georef} is {size[0]}x{size[1]}, the result's base map "
                f"{result.base_size[0]}x{result.base_size[1]}"
            )
    elif args.georef_crs:
        raise ValueError("--georef-crs goes with --georef")
    marks = None
    if args.marks:
        from registration.evaluation import read_points_csv

        marks = read_points_csv(args.marks, result.n_frames, result.frame_size, min_frames=1)
    skipped = []
    if (
        result.georef is None
        and georef is None
        and "all" in [f.strip().lower() for spec in args.formats for f in spec.split(",")]
    ):
        # 'all' of a plain base: what it can write, as the app's Export panel offers.
        skipped = [f for f in formats if f in MAP_FORMATS]
        formats = [f for f in formats if f not in MAP_FORMATS]
    options = ExportOptions(
        stage=args.stage,
        crop=args.crop,
        compress=args.compress,
        mosaic=args.mosaic,
        mosaic_frames=args.mosaic_frames,
        fps=args.fps,
        video_scale=args.video_scale,
        vector_crs=args.vector_crs,
        force=args.force,
    )
    options.validate()
    frames = open_frames(args.frames) if args.frames else None
    out_dir = Path(args.to) if args.to else Path(args.out) / "export"
    progress = LazyProgressBar("export")
    t0 = time.perf_counter()
    try:
        summary = export_result(
            result,
            out_dir,
            formats,
            frames=frames,
            georef=georef,
            marks=marks,
            options=options,
            progress=progress,
        )
    finally:
        progress.close()
    summary["total_s"] = round(time.perf_counter() - t0, 3)
    summary["skipped_formats"] = skipped
    if args.json:
        emit_json(summary)
        return 0
    sys.stdout.write(f"exported into {out_dir} in {summary['total_s']:.1f} s\n")
    if skipped:
        sys.stdout.write(
            f"  skipped {', '.join(skipped)}: they need a georeferenced base map (--georef)\n"
        )
    for fmt, paths in summary["files"].items():
        sys.stdout.write(f"  {fmt}: {len(paths)} file(s)\n")
    failed = summary.get("failed_frames") or []
    if failed:
        shown = ", ".join(map(str, failed[:10])) + (", ..." if len(failed) > 10 else "")
        sys.stdout.write(
            f"  {len(failed)} frame(s) failed in the registration and are left out: {shown}\n"
        )
    if summary.get("removed_stale"):
        sys.stdout.write(
            f"  removed {len(summary['removed_stale'])} stale file(s) of an earlier export (for "
            "frames that are failed now, or left by an interrupted export)\n"
        )
    return 0
