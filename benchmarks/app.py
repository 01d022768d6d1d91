"""Browser app: time from an interaction to the updated view, against baselines in the same run.

* Server side (real figures; 2560x1920 frames unless ``--size``): start-up to the first image;
  γ change to the preview (baseline: the full-resolution correction); seeding: a click to the
  markers drawn and to the fit (heading, scale, control points) shown; a control point disabled
  to the re-fitted table and overlays shown; scrubbing to a new frame (decoded ahead while the
  analyst looks at the previous one, and cold) and back to a seen one, against the previous
  method (warp the full frame, blend over the whole map, encode the whole map) run on the same
  frames; a click on the per-frame chart to that frame shown.
* Browser side (Debian chromium, software WebGL on this machine: an upper bound, a GPU browser
  is far faster): page load to the frame on the canvas; frame rate while panning the Seed view
  with its review overlays; playback in the Sequence view (frames handed to viser per second,
  and frames the browser shows, counted as WebGL texture uploads: :data:`JS_TEXTURES`); JS
  heap and chromium's resident memory.

Figures of the previous app (commit 40ed87e, measured the same way on this machine) are in
``BEFORE``, printed beside today's.
"""

from __future__ import annotations

import json
import tempfile
import threading
import time
from pathlib import Path

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
BEFORE = {
    "seed_click_ms": ("1.2 ms (markers only; no fit, no heading)", "the seed click"),
    "scrub_new_ms": ("453 ms", "scrub to a new frame"),
    "scrub_seen_ms": ("85 ms", "scrub back to a seen frame"),
    "plot_click_ms": ("85 ms (a click on the plot image)", "chart click to frame"),
}
"""The previous app's figures (2560x1920, 8 frames; this machine under the same shared load)."""

JS_TEXTURES = """(() => {
  // Images the browser uploads to WebGL as textures (128 px wide or more), with their times.
  // A frame handed to viser is on screen once its texture is uploaded: three.js uploads a
  // texture when it first draws it, and an image replaced before it was drawn is never
  // uploaded. (Counting changes of a canvas thumbnail instead also counted the blank moments
  // between an image removed and the next one drawn.)
  window.__texUploads = [];
  const wrap = (proto, name) => {
    const f = proto[name];
    if (!f) return;
    proto[name] = function (...args) {
      const src = args.find((a) => a && typeof a === 'object' && 'width' in a && 'height' in a);
      if (src && src.width >= 128) window.__texUploads.push(performance.now());
      return f.apply(this, args);
    };
  };
  for (const P of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
    if (P) { wrap(P.prototype, 'texImage2D'); wrap(P.prototype, 'texSubImage2D'); }
  }
})();"""
"""Installed before the page loads (``page.add_init_script``)."""

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


def _median_ms(v) -> float:
    return float(np.median(np.asarray(v)) * 1000.0)


def _old_scrub(app, k: int, stage: str) -> None:
    """The previous app's scrub step, as a same-run baseline: the full frame warped into the
    map preview's footprint box, blended over the whole map preview, encoded as one JPEG."""
    import cv2

    from app.gui import scene2d
    from registration.coords import frame_outline, rescale
    from registration.render import render_registered, viz

    r = app.state.result
    inp = app.inputs
    base_rgb = inp.base_preview(2 * app.display_max)
    hp, wp = base_rgb.shape[:2]
    f = inp.base_size[0] / wp
    warped = np.zeros_like(base_rgb)
    valid = np.zeros((hp, wp), bool)
    border = r.frame_to_base(k, frame_outline(*r.frame_size), stage)
    border = border[np.isfinite(border).all(axis=1)]
    lo = rescale(border.min(axis=0, keepdims=True), 1.0 / f)[0]
    hi = rescale(border.max(axis=0, keepdims=True), 1.0 / f)[0]
    x0, y0 = (int(max(0, np.floor(v) - 4)) for v in lo)
    x1, y1 = int(min(wp, np.ceil(hi[0]) + 5)), int(min(hp, np.ceil(hi[1]) + 5))
    frame = scene2d.to_rgb(inp.frames.get(k))  # decoded each time: the old cache held 8 frames
    crop, mask = render_registered(
        frame,
        lambda xy: r.base_to_frame(k, rescale(xy, f), stage),
        (x1 - x0, y1 - y0),
        origin=(x0, y0),
        step=8,
        return_mask=True,
    )
    warped[y0:y1, x0:x1] = crop
    valid[y0:y1, x0:x1] = mask
    img = viz.blend(warped, base_rgb, 0.5, mask=valid)
    cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])


def run(args) -> dict:
    import cv2

    from app.gui.project import Project
    from app.gui.security import make_server
    from app.gui.server import App
    from registration.lens import HarrisModel
    from registration.synth import SimConfig, load_truth, simulate

    cv2.setNumThreads(2)
    # The paper's frame size unless --size says otherwise (the benches' shared default is
    # 1280x960).
    given = getattr(args, "size_given", False)
    size = tuple(args.size_wh) if given and getattr(args, "size_wh", None) else (2560, 1920)
    n_frames = max(int(getattr(args, "frames", 6) or 6), 4)
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-app-"))
    seq = simulate(
        tmp / "seq",
        SimConfig(frame_size=size, n_frames=n_frames, video=False, seed=int(args.seed or 0)),
    )
    truth = load_truth(seq)

    t0 = time.perf_counter()
    server = make_server("127.0.0.1", 0, verbose=False)
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
    cal = app.views["Calibrate"]
    figures: dict = {"size": list(size), "n_frames": n_frames, "first_image_s": t_first}
    rows = [("Start to first image handed to viser", f"{t_first:.2f} s", "", "")]

    # γ change -> preview handed to viser (callback, correction with a new γ, JPEG encode).
    gammas = np.linspace(0.2, 0.9, 16)
    lat = []
    for g in gammas:
        t = time.perf_counter()
        cal.set_gamma(float(g))
        app.worker.wait_idle()
        lat.append(time.perf_counter() - t)
    full = []
    for g in gammas[:6] + 0.001:
        with app.state.lock:
            app.state.gamma = float(g)
        t = time.perf_counter()
        cal.render(full=True)
        full.append(time.perf_counter() - t)
    cal.set_gamma(truth.gamma)
    time.sleep(0.5)
    app.worker.wait_idle()
    figures.update(gamma_preview_ms=_median_ms(lat), gamma_full_res_ms=_median_ms(full))
    rows.append(
        (
            "γ change to preview handed to viser (1024 px JPEG), median",
            f"{figures['gamma_preview_ms']:.1f} ms",
            "",
            f"full resolution {figures['gamma_full_res_ms']:.0f} ms "
            f"({figures['gamma_full_res_ms'] / figures['gamma_preview_ms']:.1f}x)",
        )
    )

    # Seeding: the two clicks (the second completes the pair and starts the fit).
    app.set_mode("Seed")
    app.worker.wait_idle()
    seed = app.views["Seed"]
    w, h = size
    fxy = np.array([[w / 2.0, h / 2.0]])
    bxy = truth.frame_to_base(0, fxy)[0]
    corr = HarrisModel(truth.gamma, w, h).corrected_from_raw(fxy)[0]
    planes = seed.scene.planes

    def click(plane, xy):
        o, d = plane.geom.ray_towards_pixel(xy, (0.05, 0.02, -1.0))
        return app.handle_click(o, d)

    t = time.perf_counter()
    click(planes["frame"], corr)
    app.worker.wait_idle()
    t_marker = time.perf_counter() - t
    t = time.perf_counter()
    click(planes["base"], bxy)
    app.worker.wait_idle()
    t_marker2 = time.perf_counter() - t
    while app.state.current_reference() is None:
        time.sleep(0.005)
    app.worker.wait_idle()
    t_coarse = time.perf_counter() - t
    app.jobs.join(600)
    app.worker.wait_idle()
    t_fine = time.perf_counter() - t
    ref = app.state.current_reference()
    assert ref is not None and ref.fine, app.errors
    assert "heading" in seed.panel.heading_md.content
    figures.update(
        seed_click_ms=1000 * max(t_marker, t_marker2),
        seed_to_heading_s=t_coarse,
        seed_to_control_points_s=t_fine,
        n_control_points=int(len(seed.table.ids)),
    )
    rows += [
        (
            "Seed click to its marker drawn",
            f"{figures['seed_click_ms']:.1f} ms",
            BEFORE["seed_click_ms"][0],
            "",
        ),
        (
            "Seed pair complete to coarse fit, heading and scale shown",
            f"{t_coarse:.2f} s",
            "(no fit after a click)",
            "",
        ),
        (
            f"... to the fine fit and its {figures['n_control_points']} control points listed",
            f"{t_fine:.2f} s",
            "",
            "",
        ),
    ]

    # Control point disabled -> re-fit, table and overlays updated.
    refit = []
    for _ in range(5):
        rms0 = seed.table.rms
        t = time.perf_counter()
        seed.points.disable_worst()
        app.worker.wait_idle()
        refit.append(time.perf_counter() - t)
        assert seed.table.rms <= rms0 + 1e-9
    figures["disable_refit_ms"] = _median_ms(refit)
    rows.append(
        (
            "Disable the worst control point to re-fitted RMS, table and overlays shown, median",
            f"{figures['disable_refit_ms']:.0f} ms",
            "(no control-point table)",
            "",
        )
    )
    seed.points.reset_edits()
    app.worker.wait_idle()

    # Register the sequence, then scrub.
    app.set_mode("Sequence")
    seqv = app.views["Sequence"]
    t = time.perf_counter()
    assert seqv.run()
    app.jobs.join(3600)
    app.worker.wait_idle()
    figures["register_s"] = time.perf_counter() - t
    r = app.state.result
    assert r is not None and all(r.is_ok(k) for k in range(n_frames)), app.errors

    def scrub(k):
        t = time.perf_counter()
        seqv.set_frame(k)
        app.worker.wait_idle()
        return time.perf_counter() - t

    scrub(0)
    time.sleep(1.0)  # looking at frame 0: frames 1 and 2 are decoded meanwhile
    ahead = []
    for k in range(1, n_frames):
        ahead.append(scrub(k))
        time.sleep(0.6)
    seen = [scrub(k) for k in range(n_frames - 1, -1, -1)]
    # Cold: no read-ahead and nothing cached, every new frame decoded on demand.
    app.inputs.read_ahead = False
    app.inputs.clear()
    seqv.clear_cache()
    scrub(0)
    cold = [scrub(k) for k in range(1, n_frames)]
    app.inputs.read_ahead = True
    baseline = []
    for k in range(1, n_frames):
        t = time.perf_counter()
        _old_scrub(app, k, "local")
        baseline.append(time.perf_counter() - t)
    figures.update(
        scrub_new_ms=_median_ms(ahead),
        scrub_cold_ms=_median_ms(cold),
        scrub_seen_ms=_median_ms(seen),
        scrub_baseline_ms=_median_ms(baseline),
    )
    rows += [
        (
            "Scrub to a new frame (decoded ahead while the previous one is shown), median",
            f"{figures['scrub_new_ms']:.0f} ms",
            BEFORE["scrub_new_ms"][0],
            f"previous method in this run {figures['scrub_baseline_ms']:.0f} ms "
            f"({figures['scrub_baseline_ms'] / figures['scrub_new_ms']:.1f}x); aim < 100 ms",
        ),
        (
            "Scrub to a new frame, not decoded yet (a jump), median",
            f"{figures['scrub_cold_ms']:.0f} ms",
            "",
            "",
        ),
        (
            "Scrub back to a seen frame, median",
            f"{figures['scrub_seen_ms']:.0f} ms",
            BEFORE["scrub_seen_ms"][0],
            "",
        ),
    ]

    # A click on the per-frame chart (the browser script's event) to that frame shown.
    plot = []
    for k in (2, 0, 3, 1):
        t = time.perf_counter()
        app.events.dispatch(json.dumps({"kind": "plot-frame", "value": k, "n": k}))
        app.worker.wait_idle()
        plot.append(time.perf_counter() - t)
        assert app.shown["Sequence"][0] == k
    figures["plot_click_ms"] = _median_ms(plot)
    rows.append(
        (
            "Chart click to that frame shown (seen frames), median",
            f"{figures['plot_click_ms']:.0f} ms",
            BEFORE["plot_click_ms"][0],
            "",
        )
    )

    # Export from the app (a job with progress) against the library call on the same result.
    formats = ["png", "mp4", "transforms"]
    t = time.perf_counter()
    assert seqv.exporter.request(None, formats=formats)
    app.jobs.join(3600)
    app.worker.wait_idle()
    figures["export_app_s"] = time.perf_counter() - t
    assert seqv.exporter.summary is not None and not seqv.exporter.summary["cancelled"]
    from registration.gis import export_result
    from registration.io import frames

    t = time.perf_counter()
    export_result(r, tmp / "export-direct", formats, frames=frames.open_frames(seq / "frames"))
    figures["export_direct_s"] = time.perf_counter() - t
    rows.append(
        (
            f"Export {', '.join(formats)} of {n_frames} frames from the app (job with progress)",
            f"{figures['export_app_s']:.1f} s",
            "(no export in the app)",
            f"export_result directly in this run {figures['export_direct_s']:.1f} s "
            f"({figures['export_app_s'] / figures['export_direct_s']:.2f}x)",
        )
    )

    app.set_mode("Seed")
    app.worker.wait_idle()
    if CHROMIUM.exists():
        try:
            figures.update(_browser(app, rows))
        except Exception as exc:  # the server-side figures stand on their own
            rows.append(("Browser measurements", f"failed: {type(exc).__name__}: {exc}", "", ""))
    else:
        rows.append(("Browser measurements", "skipped: /usr/bin/chromium missing", "", ""))
    app.stop()

    md = [
        f"Frames {size[0]}x{size[1]}, {n_frames} frames; registering them took "
        f"{figures['register_s']:.1f} s.",
        "",
        "| measure | today | before (40ed87e) | note |",
        "|---|---:|---:|---|",
    ]
    md += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    md.append(
        "\nTimings on a 2-core machine shared with other jobs: upper bounds. Browser figures come "
        "from headless chromium with software WebGL (SwiftShader): a GPU browser is far faster."
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
        page = b.new_page(viewport={"width": 1440, "height": 900})
        page.add_init_script(JS_TEXTURES)
        t = time.perf_counter()
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function(
            "() => window.__viserMutable && window.__viserMutable.nodeRefFromName"
            " && window.__viserMutable.nodeRefFromName['/seed/base'] !== undefined"
            " && window.__viserMutable.nodeRefFromName['/seed/base'].children.length > 0",
            timeout=60000,
        )
        # The texture is on screen when the canvas centre (inside the map) is not blank.
        page.wait_for_function(
            """() => { const c = window.__viserMutable.canvas; const t = document.createElement('canvas');
              t.width = c.width; t.height = c.height; const g = t.getContext('2d'); g.drawImage(c, 0, 0);
              const d = g.getImageData(Math.floor(c.width * 0.7), Math.floor(c.height * 0.5), 1, 1).data;
              return !(d[0] > 250 && d[1] > 250 && d[2] > 250); }""",
            timeout=60000,
        )
        out["browser_first_image_s"] = time.perf_counter() - t
        time.sleep(2.0)
        fps = page.evaluate(JS_FPS, 3000)
        cdp = page.context.new_cdp_session(page)
        cdp.send("Performance.enable")
        metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        heap_mb = metrics.get("JSHeapUsedSize", float("nan")) / 2**20
        rss = _rss_mb(ours | (_chromium_pids() - before))
        out.update(fps_seed_review=fps, js_heap_mb=heap_mb, chromium_rss_mb=rss)
        # Playback in the Sequence view: the registered frames as the browser shows them.
        app.set_mode("Sequence")
        app.worker.wait_idle()
        time.sleep(2.0)
        seqv = app.views["Sequence"]
        seqv.panel.play.value = True
        time.sleep(1.0)
        # Frames the server hands to viser meanwhile (polled), against those the browser shows.
        handed, stop = [], threading.Event()

        def poll() -> None:
            last = (app.shown.get("Sequence") or (None,))[0]
            while not stop.wait(0.01):
                k = (app.shown.get("Sequence") or (None,))[0]
                if k != last:
                    handed.append(time.perf_counter())
                    last = k

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        # Rates from the first to the last event in a 10 s window (not events over the window,
        # whose edges cut a period): frames handed by the server, textures the browser uploaded.
        b0 = page.evaluate("performance.now()")
        time.sleep(10.0)
        uploads = page.evaluate(f"window.__texUploads.filter((t) => t >= {b0})")
        stop.set()
        poller.join()
        seqv.panel.play.value = False
        app.worker.wait_idle()

        def rate(times_s) -> float:
            return (len(times_s) - 1) / (times_s[-1] - times_s[0]) if len(times_s) > 2 else 0.0

        out["playback_fps"] = rate(np.asarray(uploads) / 1000.0)
        out["playback_server_fps"] = rate(handed)
        rows += [
            (
                "Page load to the Seed view on the canvas (browser)",
                f"{out['browser_first_image_s']:.2f} s",
                "",
                "upper bound",
            ),
            (
                "Frame rate panning the Seed view with its review overlays (browser)",
                f"{fps:.1f} fps",
                "",
                "software WebGL",
            ),
            (
                "Playback in the Sequence view: frames shown per second (browser)",
                f"{out['playback_fps']:.1f} fps",
                "2.5 fps (its clock)",
                f"aim >= 5 fps; frames handed to viser {out['playback_server_fps']:.1f} per s; "
                "software WebGL",
            ),
            ("JS heap (browser)", f"{heap_mb:.0f} MB", "", ""),
            ("Chromium resident memory, all processes", f"{rss:.0f} MB", "", "upper bound"),
        ]
        b.close()
    return out
