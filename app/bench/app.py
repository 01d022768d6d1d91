"""Browser app: γ preview latency at 2560x1920, start-up time, and 2000 match lines in the browser.

* Server side (real figures): time from a γ change (the callback) to the corrected preview image
  handed to viser (display resolution 1024x768, JPEG), against the full-resolution path measured
  in the same run (2560x1920 correction with new maps + JPEG) as the baseline; time from starting
  the app to the first image handed to viser.
* Browser side (Debian chromium, software WebGL on this machine: an upper bound, a GPU browser
  is far faster): time from page load to the frame on the canvas; frame rate while panning with
  the two images only and with 2000 match lines; JS heap and chromium's resident memory.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

TITLE = "Browser app (viser)"
CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--enable-precise-memory-info",
]
N_LINES = 2000

JS_FPS = """async (ms) => {
  const m = window.__viserMutable; const c = m.cameraControl; let frames = 0; let dir = 1;
  const t0 = performance.now();
  await new Promise((res) => { function step() {
      c.truck(0.002 * dir, 0, false); if (frames % 60 === 59) dir = -dir; frames++;
      if (performance.now() - t0 < ms) requestAnimationFrame(step); else res(); }
    requestAnimationFrame(step); });
  return frames / ((performance.now() - t0) / 1000);
}"""


def _chromium_pids() -> set[int]:
    pids = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if "chromium" in (d / "cmdline").read_bytes().decode(errors="replace"):
                    pids.add(int(d.name))
            except OSError:
                pass
    return pids


def _rss_mb(pids: set[int]) -> float:
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            pass
    return total / 1024.0


def _pct(v, q) -> float:
    return float(np.percentile(np.asarray(v) * 1000.0, q))


def run(args) -> dict:
    import cv2
    import viser

    from app.project import Project
    from app.server import App
    from registration.synth import SimConfig, simulate

    cv2.setNumThreads(2)
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-app-"))
    seq = simulate(
        tmp / "seq",
        SimConfig(frame_size=(2560, 1920), n_frames=2, video=False, seed=int(args.seed or 0)),
    )

    t0 = time.perf_counter()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(
        server,
        Project(tmp / "proj"),
        frames=str(seq / "frames"),
        base=str(seq / "base.png"),
        allowed_dirs=[tmp],
        display_max=1024,
    )
    app.start()
    app.worker.wait_idle()
    t_first = time.perf_counter() - t0
    assert app.shown.get("Calibrate"), "no first image"
    cal = app.tabs["Calibrate"]

    # γ change -> preview handed to viser (callback, correction with a new γ, JPEG encode).
    gammas = np.linspace(0.2, 0.9, 24)
    lat = []
    for g in gammas:
        t = time.perf_counter()
        cal.set_gamma(float(g))
        app.worker.wait_idle()
        lat.append(time.perf_counter() - t)
        assert app.shown["Calibrate"][:2] == (0, float(g))
    # Baseline: the same at full resolution (2560x1920 correction + JPEG).
    full = []
    for g in gammas[:8] + 0.001:
        with app.state.lock:
            app.state.gamma = float(g)
        t = time.perf_counter()
        cal.render(full=True)
        full.append(time.perf_counter() - t)
    time.sleep(0.5)
    app.worker.wait_idle()

    figures: dict = {
        "first_image_s": t_first,
        "gamma_preview_ms_median": _pct(lat, 50),
        "gamma_preview_ms_p90": _pct(lat, 90),
        "gamma_full_res_ms_median": _pct(full, 50),
        "preview_speedup": _pct(full, 50) / _pct(lat, 50),
    }
    rows = [
        ("Start to first image handed to viser (2560x1920 input)", f"{t_first:.2f} s", ""),
        (
            "γ change to preview handed to viser (1024x768 JPEG), median / p90",
            f"{figures['gamma_preview_ms_median']:.1f} / {figures['gamma_preview_ms_p90']:.1f} ms",
            "aim < 50 ms",
        ),
        (
            "Baseline: full-resolution 2560x1920 correction + JPEG, median",
            f"{figures['gamma_full_res_ms_median']:.1f} ms",
            f"preview {figures['preview_speedup']:.1f}x faster",
        ),
    ]

    if CHROMIUM.exists():
        try:
            figures.update(_browser(app, rows))
        except Exception as exc:  # the server-side figures stand on their own
            rows.append(("Browser measurements", f"failed: {type(exc).__name__}: {exc}", ""))
    else:
        rows.append(("Browser measurements", "skipped: /usr/bin/chromium missing", ""))
    app.stop()

    md = ["| measure | value | note |", "|---|---:|---|"]
    md += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    md.append(
        "\nBrowser figures come from headless chromium with software WebGL (SwiftShader) on 2 "
        "cores: upper bounds on cost; a GPU browser is far faster."
    )
    figures["markdown"] = "\n".join(md)
    return figures


def _browser(app, rows) -> dict:
    from playwright.sync_api import sync_playwright

    port = app.server.get_port()
    out: dict = {}
    before = _chromium_pids()
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        ours = _chromium_pids() - before
        page = b.new_page(viewport={"width": 1280, "height": 800})
        t = time.perf_counter()
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function(
            "() => window.__viserMutable && window.__viserMutable.nodeRefFromName"
            " && window.__viserMutable.nodeRefFromName['/calibrate/frame'] !== undefined"
            " && window.__viserMutable.nodeRefFromName['/calibrate/frame'].children.length > 0",
            timeout=60000,
        )
        # The texture is on screen when the canvas centre-left (inside the image) is not blank.
        page.wait_for_function(
            """() => { const c = window.__viserMutable.canvas; const t = document.createElement('canvas');
              t.width = c.width; t.height = c.height; const g = t.getContext('2d'); g.drawImage(c, 0, 0);
              const d = g.getImageData(Math.floor(c.width * 0.35), Math.floor(c.height * 0.5), 1, 1).data;
              return !(d[0] > 250 && d[1] > 250 && d[2] > 250); }""",
            timeout=60000,
        )
        out["browser_first_image_s"] = time.perf_counter() - t
        rows.append(
            (
                "Page load to frame on the canvas (browser)",
                f"{out['browser_first_image_s']:.2f} s",
                "upper bound",
            )
        )

        app.set_mode("Seed")
        app.worker.wait_idle()
        page.wait_for_function(
            "() => window.__viserMutable.nodeRefFromName['/seed/base'] !== undefined"
        )
        time.sleep(2.0)
        fps0 = page.evaluate(JS_FPS, 3000)
        seed = app.tabs["Seed"]
        rng = np.random.default_rng(0)
        w, h = app.inputs.frame_size
        bw, bh = app.inputs.base_size
        fake = SimpleNamespace(
            frame_xy=rng.uniform([0, 0], [w - 1, h - 1], (N_LINES, 2)),
            base_xy=rng.uniform([0, 0], [bw - 1, bh - 1], (N_LINES, 2)),
            gated=np.ones(N_LINES, bool),
            inliers=rng.random(N_LINES) < 0.5,
            n_matches=N_LINES,
            gate_center_base=None,
            gate_radius_base=None,
        )
        t = time.perf_counter()
        with app.server.atomic():
            seed._draw_matches(fake)
        t_add = time.perf_counter() - t
        page.wait_for_function(
            "() => window.__viserMutable.nodeRefFromName['/seed/matches'] !== undefined"
        )
        time.sleep(2.0)
        fps1 = page.evaluate(JS_FPS, 3000)
        cdp = page.context.new_cdp_session(page)
        cdp.send("Performance.enable")
        metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        heap_mb = metrics.get("JSHeapUsedSize", float("nan")) / 2**20
        rss = _rss_mb(ours | (_chromium_pids() - before))
        out.update(
            fps_images_only=fps0,
            fps_2000_lines=fps1,
            add_2000_lines_ms=t_add * 1000,
            js_heap_mb=heap_mb,
            chromium_rss_mb=rss,
        )
        rows += [
            ("Adding 2000 match lines (Python side)", f"{t_add * 1000:.1f} ms", ""),
            ("Frame rate panning, frame + map only (browser)", f"{fps0:.1f} fps", "software WebGL"),
            (
                f"Frame rate panning with {N_LINES} match lines (browser)",
                f"{fps1:.1f} fps",
                f"{fps1 / fps0:.2f}x of images only",
            ),
            ("JS heap with 2000 lines (browser)", f"{heap_mb:.0f} MB", ""),
            ("Chromium resident memory, all processes", f"{rss:.0f} MB", "upper bound"),
        ]
        b.close()
    return out
