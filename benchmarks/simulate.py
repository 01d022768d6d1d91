"""Simulator speed: city generation, one rendered frame at 1280x960 and 2560x1920 (each against
one ``cv2.warpPerspective`` of the same size, the cheapest possible "render"), truth queries, and
building the demo sequence; then every named profile (``registration.synth.PROFILES``) at
640x480, 1280x960 and 2560x1920: planning, city painting and per-frame rendering time against
``cv2.warpPerspective``, and the motion each profile delivers (measured on the truth)."""

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
    from registration.synth.plan import plan_procedural
    from registration.synth.render import FrameRenderer
    from registration.synth.truth import SimTruth

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
    prof_fig, prof_md = _profiles(seed)
    figures["profiles"] = prof_fig
    figures["markdown"] = md + "\n\n" + prof_md
    return figures


# Cities larger than this are not painted for the timing (it takes ~0.5 s per MP and ~45 bytes
# per pixel): a blank scene of the same size is sampled instead; the per-frame work (source map,
# pyramid of the frame's box, vehicles drawn from the layout, camera effects) does not depend on
# the scene's content.
PAINT_LIMIT_MP = 50.0


def _profiles(seed: int) -> tuple[dict, str]:
    from registration.synth import PROFILES
    from registration.synth import city as citymod
    from registration.synth.plan import plan_procedural
    from registration.synth.profiles import describe
    from registration.synth.render import FrameRenderer

    figures, rows = {}, []
    for name, prof in PROFILES.items():
        for size in ((640, 480), (1280, 960), (2560, 1920)):
            cfg = prof(frame_size=size, seed=seed, video=False)
            t = time.perf_counter()
            geom = plan_procedural(cfg)
            t_plan = time.perf_counter() - t
            city_mp = geom.scene_size[0] * geom.scene_size[1] / 1e6
            layout = citymod.make_layout(*geom.scene_size, gsd=cfg.gsd_m, seed=cfg.seed)
            t = time.perf_counter()
            if city_mp <= PAINT_LIMIT_MP:
                scene = citymod.render_city(layout, citymod.Look(parked_seed=cfg.seed * 2 + 1))
                t_paint = time.perf_counter() - t
            else:
                scene = np.zeros((geom.scene_size[1], geom.scene_size[0], 3), np.uint8)
                t_paint = float("nan")
            renderer = FrameRenderer(geom, scene, cfg, layout)
            picks = [0] if size[0] >= 2560 else [0, geom.n_frames // 2, geom.n_frames - 1]
            times = []
            for k in picks:
                t = time.perf_counter()
                renderer.render(k)
                times.append(time.perf_counter() - t)
            # The first frame also builds the static pyramid when there are no vehicles; with
            # vehicles (all profiles here) every frame does the same work.
            t_frame = min(times)
            h = np.array([[1.02, 0.05, -30.0], [-0.05, 1.02, -20.0], [0.0, 0.0, 1.0]])
            src = scene[: size[1] * 2, : size[0] * 2]
            t_warp = _best(
                lambda s=src, h=h, z=size: cv2.warpPerspective(s, h, z, flags=cv2.INTER_LINEAR)
            )
            key = f"{name} {size[0]}x{size[1]}"
            figures[key] = {
                "plan_s": t_plan,
                "city_px": list(geom.scene_size),
                "city_paint_s": None if np.isnan(t_paint) else t_paint,
                "frame_s": t_frame,
                "frames_timed": len(times),
                "warpPerspective_s": t_warp,
                "frame_over_warp": t_frame / t_warp,
            }
            paint = "blank*" if np.isnan(t_paint) else f"{t_paint:.1f}"
            rows.append(
                f"| {name} | {size[0]}x{size[1]} | {cfg.n_frames} | {t_plan:.2f} | "
                f"{geom.scene_size[0]}x{geom.scene_size[1]} ({city_mp:.0f} MP) | {paint} | "
                f"{t_frame * 1000:.0f} ({len(times)}) | {t_warp * 1000:.2f} | "
                f"{t_frame / t_warp:.0f}x |"
            )
            del scene, renderer
    motion_rows = []
    for name in PROFILES:
        for size in ((640, 480), (2560, 1920)):
            d = describe(name, size, seeds=(0, 1, 2))
            figures[f"{name} {size[0]}x{size[1]} motion"] = d
            fit = d["harris_fit"]
            motion_rows.append(
                f"| {name} | {size[0]}x{size[1]} | {d['unregistered_mean_px']:.1f} +- "
                f"{d['unregistered_std_px']:.1f} | {d['interframe_mean_px']:.1f} / "
                f"{d['interframe_max_px']:.1f} | {d['shake_mean_deg']:.2f} / "
                f"{d['shake_max_deg']:.2f} | {d['last_sees_of_first_max']:.2f} | "
                f"{fit['corner_px']:.2f} (gamma {fit['gamma']:.3f}) |"
            )
    md = (
        "Profiles: time per rendered frame (best of the frames timed) against one "
        "cv2.warpPerspective of the same size, in the same run.\n\n"
        "| profile | frame | frames | plan s | city | paint s | one frame ms (n) | "
        "warpPerspective ms | ratio |\n|---|---|---|---|---|---|---|---|---|\n"
        + "\n".join(rows)
        + f"\n\n\\* city over {PAINT_LIMIT_MP:.0f} MP: not painted for the timing (a blank scene "
        "of the same size is sampled; the per-frame work does not depend on the content).\n\n"
        "Profiles: motion delivered (truth, seeds 0-2; table-2 'Unregistered' = 5 points over "
        "10 frames spread over the flight, radially corrected px from the first frame).\n\n"
        "| profile | frame | unregistered mu +- sigma px | frame-to-frame mean / max px | "
        "shake mean / max deg | last frame sees of first | Harris-fit corner residual px |\n"
        "|---|---|---|---|---|---|---|\n" + "\n".join(motion_rows)
    )
    return figures, md
