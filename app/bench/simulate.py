"""Simulator speed: city generation, one rendered frame at 1280x960 and 2560x1920 (each against
one ``cv2.warpPerspective`` of the same size, the cheapest possible "render"), truth queries, and
building the demo sequence."""

from __future__ import annotations

import os
import tempfile
import time

import cv2
import numpy as np

TITLE = "Simulator (registration.synth)"


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def run(args) -> dict:
    from registration.synth import SimConfig, demo
    from registration.synth import city as citymod
    from registration.synth.sequence import FrameRenderer, SimTruth, plan_procedural

    cv2.setNumThreads(2)
    seed = int(getattr(args, "seed", 0) or 0)
    rows, figures = [], {}
    for size in ((1280, 960), (2560, 1920)):
        cfg = SimConfig(frame_size=size, n_frames=3, seed=seed, video=False)
        geom = plan_procedural(cfg)
        t = time.perf_counter()
        layout = citymod.make_layout(*geom.scene_size, gsd=cfg.gsd_m, seed=seed)
        scene = citymod.render_city(layout)
        t_city = time.perf_counter() - t
        t = time.perf_counter()
        citymod.second_sensor(
            citymod.render_city(layout, citymod.Look(parked_seed=2, traffic_seed=1)), seed
        )
        t_base = time.perf_counter() - t
        renderer = FrameRenderer(geom, scene, cfg, layout)
        renderer.render(0)  # warm-up (pyramid of the static scene, caches)
        t_frame = _best(lambda r=renderer: r.render(1))
        h = np.array([[1.02, 0.05, -300.0], [-0.05, 1.02, -200.0], [0.0, 0.0, 1.0]])
        t_warp = _best(
            lambda s=scene, h=h, z=size: cv2.warpPerspective(s, h, z, flags=cv2.INTER_LINEAR)
        )
        truth = SimTruth(geom)
        q = np.random.default_rng(0).uniform([0, 0], [size[0] - 1, size[1] - 1], (10000, 2))
        t_f2b = _best(lambda tr=truth, q=q: tr.frame_to_base(1, q))
        b = truth.frame_to_base(1, q)
        t_b2f = _best(lambda tr=truth, b=b: tr.base_to_frame(1, b))
        key = f"{size[0]}x{size[1]}"
        figures[key] = {
            "city_px": list(geom.scene_size),
            "city_s": t_city,
            "base_second_sensor_s": t_base,
            "frame_s": t_frame,
            "warpPerspective_s": t_warp,
            "frame_over_warp": t_frame / t_warp,
            "frame_to_base_10k_s": t_f2b,
            "base_to_frame_10k_s": t_b2f,
        }
        rows.append(
            f"| {key} | {geom.scene_size[0]}x{geom.scene_size[1]} | {t_city:.2f} | {t_base:.2f} | "
            f"{t_frame * 1000:.0f} | {t_warp * 1000:.1f} | {t_frame / t_warp:.0f}x | "
            f"{t_f2b * 1000:.1f} / {t_b2f * 1000:.1f} |"
        )
    # The demo, built from scratch into a temporary cache (the user's cache is left alone).
    old = os.environ.get("AERIALREG_CACHE_DIR")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["AERIALREG_CACHE_DIR"] = tmp
        try:
            t = time.perf_counter()
            demo.demo_sequence()
            t_demo = time.perf_counter() - t
            t = time.perf_counter()
            demo.demo_sequence()
            t_cached = time.perf_counter() - t
        finally:
            if old is None:
                os.environ.pop("AERIALREG_CACHE_DIR", None)
            else:
                os.environ["AERIALREG_CACHE_DIR"] = old
    dc = demo.DEMO_CONFIG
    figures["demo"] = {
        "build_s": t_demo,
        "cached_check_s": t_cached,
        "frames": dc.n_frames,
        "frame_size": list(dc.frame_size),
    }
    md = (
        "| frame | city (auto) px | city s | base (2nd sensor) s | one frame ms | warpPerspective ms | ratio | truth 10k pts f2b / b2f ms |\n"
        "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n\n"
        f"Demo ({dc.frame_size[0]}x{dc.frame_size[1]}, {dc.n_frames} frames, with PNG + MP4 writing): "
        f"built in {t_demo:.1f} s; reopening the cache (manifest check) {t_cached * 1000:.0f} ms."
    )
    figures["markdown"] = md
    return figures
