"""Scale-out on Dask: throughput of one simulated sequence registered serially (one chunk, the
paper's chain), serially in chunks, and in the same chunks on local Dask clusters of 1, 2, ...
workers; the chunked runs' agreement with the serial chunked run and everyone's error against
the exact truth."""

from __future__ import annotations

import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TITLE = "Scale-out: serial vs chunked vs Dask LocalCluster workers"


def _error(result, truth, grid) -> float:
    """Mean distance (base px) of a 9x7 grid of every frame to the truth, stage local."""
    errs = [
        np.nanmean(np.hypot(*(result.frame_to_base(k, grid) - truth.frame_to_base(k, grid)).T))
        for k in range(result.n_frames)
    ]
    return float(np.mean(errs))


def _gap(a, b, grid) -> tuple[float, float]:
    """Largest and mean distance (base px) between two results over a grid of every frame and
    both stages."""
    gaps = []
    for k in range(a.n_frames):
        for stage in ("global", "local"):
            pa, pb = a.frame_to_base(k, grid, stage), b.frame_to_base(k, grid, stage)
            d = np.hypot(*(pa - pb).T)
            gaps.append(d[np.isfinite(d)])
    d = np.concatenate(gaps)
    return (float(d.max()), float(d.mean())) if len(d) else (0.0, 0.0)


def run(args) -> dict:
    import logging

    from benchmarks.sequence import simulated_sequence
    from registration.run import (
        DaskExecutor,
        chunk_plan,
        get_preset,
        open_client,
        register_sequence,
        require_distributed,
    )

    require_distributed()  # importing it sets its loggers' levels
    logging.getLogger("distributed").setLevel(logging.WARNING)
    w, h = args.size_wh
    n = args.frames
    ref = n // 2
    chunk = args.chunk_frames or max(1, math.ceil((n - 1 - ref) / 2))
    workers = args.workers_list
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-"))
    seq = simulated_sequence(args, tmp / "sim", "bench scaleout", reference_frame=ref)
    truth, frames, base, seed = seq.truth, seq.frames, seq.base, seq.seed
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7))
    grid = np.c_[gx.ravel(), gy.ravel()]
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 25), np.linspace(0, h - 1, 19))
    dense = np.c_[gx.ravel(), gy.ravel()]
    preset = get_preset("default")

    def register(name, config, executor=None) -> dict:
        marks = {}

        def progress(done, total):
            if done >= 1 and "reference" not in marks:
                marks["reference"] = time.perf_counter()

        t1 = time.perf_counter()
        result = register_sequence(
            frames, base, truth.gamma, tmp / name, config=config, preset="default", seed=seed,
            reference_frame=ref, progress=progress, executor=executor,
        )  # fmt: skip
        t2 = time.perf_counter()
        after_ref = t2 - marks.get("reference", t1)
        row = {
            "wall_s": t2 - t1,
            "fps": n / (t2 - t1),
            "fps_after_reference": (n - 1) / after_ref if after_ref > 0 else float("nan"),
            "error_px": _error(result, truth, grid),
            "n_failed": sum(r.status != "ok" for r in result.records),
            "result": result,
        }
        sys.stderr.write(f"bench scaleout: {name} {row['wall_s']:.1f} s\n")
        return row

    rows = {"serial": register("serial", preset)}
    chunked = dataclasses.replace(preset, chunk_frames=chunk)
    rows["chunked"] = register("chunked", chunked)
    for nw in workers:
        t1 = time.perf_counter()
        with open_client(workers=nw) as client:
            start_s = time.perf_counter() - t1
            row = register(f"dask{nw}", chunked, DaskExecutor(client))
        row["cluster_start_s"] = start_s
        rows[f"dask{nw}"] = row
    for row in rows.values():
        row["gap_max_px"], row["gap_mean_px"] = _gap(
            row["result"], rows["chunked"]["result"], dense
        )
    for row in rows.values():
        del row["result"]

    n_chunks = len(chunk_plan(n, ref, chunk))
    base_fps = rows["serial"]["fps_after_reference"]
    lines = [
        f"Sequence: {n} simulated frames {w}x{h} ({args.profile or 'default'} flight, seed "
        f"{args.seed}), reference frame {ref}, "
        f"default preset; chunked runs: --chunk-frames {chunk} ({n_chunks} chunks). Frames/s over "
        "the whole run and after the reference frame (which the driver registers alone first); "
        "Dask rows exclude starting the local cluster and importing aerialreg in its workers (their "
        "own column). Gap: largest and mean distance between the run and the serial chunked run "
        "over a 25x19 grid of every frame, both stages; error: mean distance to the exact truth, "
        "9x7 grid, stage local.",
        "",
        "| run | wall s | frames/s | frames/s after reference | vs serial | cluster start s | gap to chunked max / mean px | error vs truth px |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    names = {"serial": "serial, one chunk", "chunked": f"serial, chunks of {chunk}"}
    for key, r in rows.items():
        name = names.get(key, f"Dask LocalCluster, {key[4:]} worker(s)")
        start = f"{r['cluster_start_s']:.1f}" if "cluster_start_s" in r else ""
        lines.append(
            f"| {name} | {r['wall_s']:.1f} | {r['fps']:.2f} | {r['fps_after_reference']:.2f} | "
            f"{r['fps_after_reference'] / base_fps:.2f}x | {start} | {r['gap_max_px']:.3f} / "
            f"{r['gap_mean_px']:.3f} | "
            f"{r['error_px']:.2f} |"
        )
    return {
        "size": [w, h],
        "frames": n,
        "reference_frame": ref,
        "chunk_frames": chunk,
        "n_chunks": n_chunks,
        "rows": rows,
        "markdown": "\n".join(lines),
    }
