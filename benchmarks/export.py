"""GIS export speed: writing a registered frame as GeoTIFF (plain, deflate, COG) and PNG + world
file, and a sequence's mosaic, each beside ``cv2.imwrite`` of the same pixels in the same run.

A simulated sequence (``--size``, ``--frames``) is registered against its base map given a
synthetic UTM georeference; the per-frame figures use each registered frame rendered into its
footprint (the pixels ``aerialreg export`` writes), the mosaic figures the whole sequence.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

TITLE = "GIS export: GeoTIFF / COG / PNG + world file and mosaic vs cv2.imwrite"
REPEAT = 3
# A plausible UTM grid for the simulated base map (0.3 m pixels, like the procedural city).
TRANSFORM = (0.3, 0.0, 512000.0, 0.0, -0.3, 4123000.0)


def _time(fn, repeat: int = REPEAT) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _frame_writers(tmp: Path, georef):
    from registration.gis import write_geotiff, write_png_georeferenced

    return {
        "cv2.imwrite PNG (baseline)": lambda im, m: cv2.imwrite(str(tmp / "a.png"), im),
        "cv2.imwrite TIFF": lambda im, m: cv2.imwrite(str(tmp / "a.tif"), im),
        "GeoTIFF, no compression": lambda im, m: write_geotiff(
            tmp / "b.tif", im, georef, mask=m, compress="none"
        ),
        "GeoTIFF, deflate (default)": lambda im, m: write_geotiff(
            tmp / "c.tif", im, georef, mask=m
        ),
        "GeoTIFF, deflate, 2 threads": lambda im, m: write_geotiff(
            tmp / "d.tif", im, georef, mask=m, num_threads=2
        ),
        "GeoTIFF, lzw": lambda im, m: write_geotiff(
            tmp / "e.tif", im, georef, mask=m, compress="lzw"
        ),
        "COG, deflate (with overviews)": lambda im, m: write_geotiff(
            tmp / "f.tif", im, georef, mask=m, cog=True
        ),
        "PNG + alpha + world file + CRS sidecars": lambda im, m: write_png_georeferenced(
            tmp / "g.png", im, georef, mask=m
        ),
    }


def run(args) -> dict:
    import shutil

    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-export-"))
    try:
        return _run(args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # GeoTIFFs of 25 Mpx frames add up


def _run(args, tmp: Path) -> dict:
    from pyproj import CRS

    from registration.gis import ExportOptions, GeoReference, export_result, write_geotiff
    from registration.gis.export import _Mosaic, _render_frame
    from registration.io import open_frames, read_image
    from registration.run import get_preset, register_sequence
    from registration.synth import SimConfig, load_truth, simulate

    w, h = args.size_wh
    cfg = SimConfig(frame_size=(w, h), n_frames=args.frames, seed=args.seed, video=False)
    simulate(tmp / "sim", cfg, scene=args.scene, base=args.base)
    truth = load_truth(tmp / "sim")
    frames = open_frames(tmp / "sim" / "frames")
    georef = GeoReference(TRANSFORM, CRS.from_epsg(32633).to_wkt())
    bx, by = truth.frame_to_base(0, [[w / 2, h / 2]])[0]
    result = register_sequence(
        frames,
        read_image(tmp / "sim" / "base.png"),
        truth.gamma,
        tmp / "reg",
        config=get_preset("default"),
        seed=(w / 2, h / 2, float(bx), float(by)),
        base_georef=georef,
    )
    ok = [k for k in range(result.n_frames) if result.is_ok(k)]
    sys.stderr.write(f"bench export: registered {len(ok)}/{result.n_frames} frames {w}x{h}\n")

    # Per frame: the registered frames as export renders them.
    rendered = []
    render_t = []
    for k in ok:
        t0 = time.perf_counter()
        img, mask, box = _render_frame(result, frames.get(k), k, "local", result.base_size, 8)
        render_t.append(time.perf_counter() - t0)
        if img is not None:
            rendered.append((img, mask, box))
    writers = _frame_writers(tmp, None)
    per_frame = {name: [] for name in writers}
    sizes = {}
    for img, mask, box in rendered:
        for name, fn in _frame_writers(tmp, georef.cropped(box[0], box[1])).items():
            per_frame[name].append(_time(lambda fn=fn, img=img, mask=mask: fn(img, mask)))
    for name, path in zip(
        writers,
        ["a.png", "a.tif", "b.tif", "c.tif", "d.tif", "e.tif", "f.tif", "g.png"],
        strict=True,
    ):
        sizes[name] = (tmp / path).stat().st_size / 1e6
    frame_rows = {name: float(np.mean(v)) for name, v in per_frame.items()}
    base_s = frame_rows["cv2.imwrite PNG (baseline)"]
    mean_px = float(np.mean([im.shape[0] * im.shape[1] for im, _, _ in rendered]))

    # Per sequence: mosaic (median and mean) and the whole export.
    from registration.render import footprint

    seq = footprint(
        [lambda q, k=k: result.frame_to_base(k, q, "local") for k in ok],
        tuple(result.frame_size),
        tuple(result.base_size),
        pad=2,
    )
    mosaic_rows = {}
    for method in ("median", "mean"):
        t0 = time.perf_counter()
        mosaic = _Mosaic(seq, method, len(rendered))
        for img, mask, box in rendered:
            mosaic.add(img, mask, box)
        image, valid = mosaic.result()
        mosaic_rows[f"combine ({method}, {len(rendered)} frames)"] = time.perf_counter() - t0
    gr_seq = georef.cropped(seq[0], seq[1])

    mosaic_rows["cv2.imwrite PNG of the mosaic (baseline)"] = _time(
        lambda: cv2.imwrite(str(tmp / "m.png"), image)
    )
    mosaic_rows["mosaic COG write"] = _time(
        lambda: write_geotiff(tmp / "m.tif", image, gr_seq, mask=valid, cog=True)
    )
    t0 = time.perf_counter()
    summary = export_result(
        result,
        tmp / "export",
        ["geotiff", "mosaic", "mp4", "points", "geojson"],
        frames=frames,
        options=ExportOptions(),
    )
    total = time.perf_counter() - t0
    steps = summary["time_s"]

    md = [
        f"{len(rendered)} registered frames of a simulated {w}x{h} sequence, each rendered into "
        f"its footprint (mean {mean_px / 1e6:.2f} Mpx); median of {REPEAT} writes each, mean over "
        "frames; ratio = time / cv2.imwrite PNG of the same pixels in this run. Timings on a "
        "shared 2-core machine: upper bounds.",
        "",
        "| per frame | time s | ratio | file MB |",
        "|---|---:|---:|---:|",
        f"| render into base pixels (registration mapping + remap) | {np.mean(render_t):.3f} | "
        f"{np.mean(render_t) / base_s:.1f} | |",
        *(
            f"| {name} | {t:.3f} | {t / base_s:.1f} | {sizes[name]:.1f} |"
            for name, t in frame_rows.items()
        ),
        "",
        f"Mosaic over the sequence footprint {seq[2]}x{seq[3]} px:",
        "",
        "| per sequence | time s |",
        "|---|---:|",
        *(f"| {name} | {t:.3f} |" for name, t in mosaic_rows.items()),
        f"| whole `aerialreg export` (geotiff, mosaic, mp4, points, geojson) | {total:.2f} |",
        "",
        "Inside that export: "
        + ", ".join(f"{k} {v:.2f} s" for k, v in steps.items())
        + " (render = all frames).",
    ]
    return {
        "frame_size": [w, h],
        "n_frames": len(rendered),
        "mean_frame_px": mean_px,
        "render_s": float(np.mean(render_t)),
        "per_frame_s": frame_rows,
        "per_frame_ratio": {k: v / base_s for k, v in frame_rows.items()},
        "file_mb": sizes,
        "sequence_box": list(seq),
        "mosaic_s": mosaic_rows,
        "export_total_s": total,
        "export_steps_s": steps,
        "markdown": "\n".join(md),
    }
