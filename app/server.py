"""The analyst's browser app (viser): γ calibration, click-to-seed, match and residual review.

Structure (``notes/viser.md``, ``notes/style.md`` practice 12):

* :class:`App` owns the viser server, the one :class:`~app.state.AppState` (one lock), the
  project folder, one :class:`~app.worker.LatestWorker` for interactive renders (latest request
  wins) and one :class:`~app.worker.JobRunner` for long runs (demo build, registration).
* One view per step (Calibrate, Seed, Sequence, Evaluate), chosen with the "View" buttons; each
  view is a module ``app/tab_*.py`` owning its GUI folder and scene node.
* GUI callbacks only update state and post requests; scene drawing happens on the worker.
* Clicks on the scene arrive as rays; :meth:`App.handle_click` intersects them with the image
  planes of the current view (``app.scene2d``) and hands pixel coordinates to the view.

Nothing here computes registration results: every number and image comes from ``registration``.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from app import scene2d, security
from app.project import Project, default_project_dir
from app.security import escape_md, resolve_allowed
from app.state import MODES, AppState
from app.worker import JobRunner, LatestWorker

log = logging.getLogger(__name__)

PAN_ONLY_JS = """const f = () => { const m = window.__viserMutable;
  if (!m || !m.cameraControl) return setTimeout(f, 100); const c = m.cameraControl;
  c.mouseButtons.left = 2; c.mouseButtons.right = 2;
  c.touches.one = 128; c.dollyToCursor = true; };  f();"""
"""Left-drag pans instead of orbiting, the wheel zooms to the cursor (private viser hook; see
notes/viser.md section 2 — harmless if a viser upgrade breaks it: orbiting comes back)."""


class Inputs:
    """The opened frame source and base map (read-only once built)."""

    def __init__(self, frames_path: str, base_path: str) -> None:
        from registration import io

        self.frames_path, self.base_path = str(frames_path), str(base_path)
        self.frames = io.open_frames(frames_path)
        self.base = io.read_image(base_path)
        self.n_frames = len(self.frames)
        self.frame_size = tuple(int(v) for v in self.frames.size)
        self.base_size = (int(self.base.shape[1]), int(self.base.shape[0]))
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._previews: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def preview(self, k: int, max_side: int) -> np.ndarray:
        """Raw frame ``k`` downscaled to at most ``max_side`` pixels (BGR), cached."""
        key = (k, max_side)
        with self._lock:
            if key in self._previews:
                self._previews.move_to_end(key)
                return self._previews[key]
        img = scene2d.preview(self.frame(k), max_side)
        with self._lock:
            self._previews[key] = img
            while len(self._previews) > 8:
                self._previews.popitem(last=False)
        return img

    def frame(self, k: int) -> np.ndarray:
        """Raw frame ``k`` (BGR uint8), with a small LRU cache (videos decode slowly)."""
        if not 0 <= k < self.n_frames:
            raise ValueError(f"frame {k} out of range 0..{self.n_frames - 1}")
        with self._lock:
            if k in self._cache:
                self._cache.move_to_end(k)
                return self._cache[k]
        img = self.frames.get(k)
        with self._lock:
            self._cache[k] = img
            while len(self._cache) > 8:
                self._cache.popitem(last=False)
        return img


class App:
    """The running app. Construct, then :meth:`start`; :meth:`stop` ends it.

    Args:
        server: a viser server (the caller chooses host/port).
        project: the project folder.
        frames, base: input paths; None for both = the saved inputs or the built-in demo.
        allowed_dirs: folders the browser's path field may open from.
        max_upload_mb: uploads larger than this are rejected with a notification.
        display_max: longest side in pixels of images sent to the browser for frames;
            the base map is sent at up to twice that.
        demo_builder: returns the demo folder (frames/, base.png); default
            ``registration.synth.demo_sequence``; tests inject a small one.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        project: Project,
        *,
        frames: str | None = None,
        base: str | None = None,
        allowed_dirs: list[Path] | None = None,
        max_upload_mb: float = 500.0,
        display_max: int = 1024,
        demo_builder: Callable[..., Path] | None = None,
        project_is_explicit: bool = True,
    ) -> None:
        self.server = server
        self.project = project
        self.project_is_explicit = project_is_explicit
        self.state = AppState()
        self.worker = LatestWorker(on_error=self._report_error)
        self.jobs = JobRunner(on_error=self._report_error)
        self.max_upload_bytes = int(max_upload_mb * 1024 * 1024)
        self.display_max = int(display_max)
        self.allowed_dirs = [Path(p).expanduser().resolve() for p in (allowed_dirs or [])]
        self.inputs: Inputs | None = None
        self.demo_builder = demo_builder
        self.shown: dict[str, Any] = {}  # what each view last handed to viser (tests, bench)
        self._cli_inputs = (frames, base)
        self.tabs: dict[str, Any] = {}
        self.errors: list[str] = []  # last error messages (tests read them)
        self.notices: list[tuple[str, str, str]] = []  # last notifications (title, body, colour)

    # ------------------------------------------------------------------ setup
    def start(self) -> None:
        from app.tab_calibrate import CalibrateTab
        from app.tab_evaluate import EvaluateTab
        from app.tab_seed import SeedTab
        from app.tab_sequence import SequenceTab

        server = self.server
        server.gui.configure_theme(
            control_width="large", show_share_button=False, show_logo=False, dark_mode=False
        )
        # Hiding the share button is not enough: any client can still ask for the tunnel.
        security.refuse_share_tunnel(server)
        security.install_upload_limit(server, self.max_upload_bytes, self._upload_refused)
        # Dock the panel beside the canvas so it never covers the images.
        server.gui.main_panel.dock_right()
        from viser import _messages

        server.gui._websock_interface.queue_message(
            _messages.RunJavascriptMessage(source=PAN_ONLY_JS)
        )
        server.initial_camera.position = (0.0, 0.0, -2.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, -1.0, 0.0)

        try:
            session = self.project.load()
        except ValueError as exc:
            self._remember_error(str(exc))
            session = {}
        with self.state.lock:
            self.state.apply_session(session)

        self.status = server.gui.add_markdown("**aerialreg** starting ...")
        self.progress = server.gui.add_progress_bar(0.0, visible=False)
        self.mode_buttons = server.gui.add_button_group("View", list(MODES))
        self.mode_buttons.on_click(lambda ev: self.set_mode(ev.target.value))
        self._build_inputs_folder()
        for cls in (CalibrateTab, SeedTab, SequenceTab, EvaluateTab):
            tab = cls(self)
            self.tabs[tab.MODE] = tab
        server.scene.on_click()(self._on_scene_click)
        server.on_client_connect(self._on_connect)

        frames, base = self._cli_inputs
        if frames or base:
            if not (frames and base):
                raise ValueError("--frames and --base go together")
            self.open_inputs(frames, base, client=None)
        elif self.state.frames_path and self.state.base_path:
            try:
                self.open_inputs(self.state.frames_path, self.state.base_path, client=None)
            except (OSError, ValueError) as exc:
                self._remember_error(f"could not reopen saved inputs: {exc}")
                self._start_demo()
        else:
            self._start_demo()
        self.set_mode(self.state.mode)

    def _build_inputs_folder(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Inputs", expand_by_default=False):
            self.frames_text = gui.add_text("Frames (video, folder, glob)", "")
            self.base_text = gui.add_text("Base map image", "")
            open_btn = gui.add_button("Open paths")
            open_btn.on_click(lambda ev: self.open_paths_from_gui(ev.client))
            self.upload_frames = gui.add_upload_button("Upload frames (video)", icon=None)
            self.upload_frames.on_upload(
                lambda ev: self.handle_upload("frames", ev.target.value, ev.client)
            )
            self.upload_base = gui.add_upload_button("Upload base map", icon=None)
            self.upload_base.on_upload(
                lambda ev: self.handle_upload("base", ev.target.value, ev.client)
            )
            self.inputs_md = gui.add_markdown("")
        self._update_inputs_md()

    def allowed_roots(self) -> list[Path]:
        """Folders the browser may open files from: the ones given at start (--allow-dir, the
        inputs' folders) and the current project (its uploads)."""
        roots = list(self.allowed_dirs)
        if self.project.folder not in roots:
            roots.append(self.project.folder)
        return roots

    def _update_inputs_md(self) -> None:
        allowed = ", ".join(escape_md(p) for p in self.allowed_roots())
        self.inputs_md.content = (
            f"Project: {escape_md(self.project.folder)}  \nPaths may lie under: {allowed}  \n"
            f"Uploads up to {_size(self.max_upload_bytes)}."
        )

    # ------------------------------------------------------------------ inputs
    def _start_demo(self) -> None:
        self.set_status("Building the built-in demo sequence (first use only) ...")

        def build(cancel: threading.Event) -> None:
            builder = self.demo_builder
            if builder is None:
                from registration.synth import demo_sequence as builder
            from app.progress import ProgressBar

            bar_holder: dict[str, ProgressBar] = {}

            def progress(done: int, total: int) -> None:
                # registration.synth's progress protocol: (steps done, total steps).
                percent = 100.0 * done / max(total, 1)
                self.set_progress(percent)
                if "bar" not in bar_holder:
                    bar_holder["bar"] = ProgressBar(100, "demo").__enter__()
                bar = bar_holder["bar"]
                bar.update(int(round(percent)) - bar.done)

            folder = Path(builder(progress=progress))
            if "bar" in bar_holder:
                bar_holder["bar"].__exit__(None, None, None)
            self.set_progress(None)
            self.open_inputs(str(folder / "frames"), str(folder / "base.png"), client=None)
            self.set_mode(self.state.mode)

        self.jobs.start("demo", build)

    def open_paths_from_gui(self, client) -> None:
        """The "Open paths" button: check both paths against the allowed folders, then open."""
        try:
            frames = resolve_allowed(self.frames_text.value, self.allowed_roots())
            base = resolve_allowed(self.base_text.value, self.allowed_roots())
        except (ValueError, FileNotFoundError) as exc:
            self.notify(client, "Path refused", str(exc), color="red")
            return
        self.worker.submit("open", lambda: self._open_and_report(str(frames), str(base), client))

    def _open_and_report(self, frames: str, base: str, client) -> None:
        try:
            self.open_inputs(frames, base, client=client)
        except (OSError, ValueError, IndexError) as exc:
            self.notify(client, "Could not open inputs", str(exc), color="red")
            return
        self.set_mode(self.state.mode)
        self.notify(client, "Inputs opened", f"{frames}\n{base}", color="green")

    def _upload_refused(self, client_id: int, name: str, size: int) -> None:
        """The upload guard refused a transfer while it arrived (security.install_upload_limit)."""
        client = self.server.get_clients().get(client_id)
        self.notify(
            client,
            "Upload refused",
            f"{name} is {_size(size)}; the limit is {_size(self.max_upload_bytes)} "
            "(--max-upload-mb)",
            color="red",
        )

    def handle_upload(self, kind: str, uploaded, client) -> None:
        """Save an uploaded file under the project (size-checked) and open it.

        The other input is taken from its text box, checked against the allowed folders like a
        typed path (an upload must not open an unchecked path)."""
        name = Path(getattr(uploaded, "name", "") or "upload").name
        content = getattr(uploaded, "content", b"") or b""
        if len(content) > self.max_upload_bytes:
            self.notify(
                client,
                "Upload refused",
                f"{name} is {_size(len(content))}; the limit is "
                f"{_size(self.max_upload_bytes)} (--max-upload-mb)",
                color="red",
            )
            return
        if not content:
            self.notify(client, "Upload refused", f"{name} is empty", color="red")
            return
        safe = (
            "".join(c if c.isalnum() or c in "-_." else "_" for c in name).lstrip(".") or "upload"
        )
        path = self.project.uploads_dir / f"{kind}-{safe}"
        self.project.write_file(str(path.relative_to(self.project.folder)), content)
        if kind == "frames":
            self.frames_text.value = str(path)
        else:
            self.base_text.value = str(path)
        other = self.base_text.value if kind == "frames" else self.frames_text.value
        if not other:
            self.notify(
                client, "Uploaded", f"{name} saved; now choose the other input", color="blue"
            )
            return
        try:
            other_path = str(resolve_allowed(other, self.allowed_roots()))
        except (ValueError, FileNotFoundError) as exc:
            self.notify(client, "Path refused", str(exc), color="red")
            return
        frames, base = (str(path), other_path) if kind == "frames" else (other_path, str(path))
        self.worker.submit("open", lambda: self._open_and_report(frames, base, client))

    def open_inputs(self, frames: str, base: str, client) -> None:
        """Open inputs (raises on unusable ones) and reset everything that depends on them."""
        inputs = Inputs(frames, base)
        with self.state.lock:
            st = self.state
            same = st.frames_path == inputs.frames_path and st.base_path == inputs.base_path
            if not same:
                # New inputs: switch to their own project unless one was given explicitly.
                if not self.project_is_explicit and st.frames_path is not None:
                    self.project = Project(default_project_dir(frames, base))
                    st.apply_session(self.project.load())
                    same = st.frames_path == inputs.frames_path and st.base_path == inputs.base_path
            if not same:
                st.lines, st.line_open, st.seed_frame, st.seed_base = [], False, None, None
                st.coarse = st.fine = None
                st.result_dir = None
                st.points = {}
                st.calib_frame = st.seq_frame = st.eval_frame = st.reference_frame = 0
            st.frames_path, st.base_path = inputs.frames_path, inputs.base_path
            st.n_frames, st.frame_size, st.base_size = (
                inputs.n_frames,
                inputs.frame_size,
                inputs.base_size,
            )
            for name in ("calib_frame", "seq_frame", "eval_frame", "reference_frame"):
                setattr(st, name, int(np.clip(getattr(st, name), 0, inputs.n_frames - 1)))
            self.inputs = inputs
            st.revision += 1
        self.frames_text.value = inputs.frames_path
        self.base_text.value = inputs.base_path
        # Uploads no input refers to any more are removed (they can be hundreds of MB).
        self.project.prune_uploads([inputs.frames_path, inputs.base_path])
        self._update_inputs_md()
        for tab in self.tabs.values():
            tab.on_inputs()
        self.save()
        self.set_status(
            f"**{Path(inputs.frames_path).name}**: {inputs.n_frames} frames "
            f"{inputs.frame_size[0]}x{inputs.frame_size[1]}; base "
            f"{inputs.base_size[0]}x{inputs.base_size[1]}"
        )

    # ------------------------------------------------------------------ views and clicks
    def set_mode(self, mode: str) -> None:
        if mode not in MODES:
            return
        with self.state.lock:
            self.state.mode = mode
        for name, tab in self.tabs.items():
            tab.set_visible(name == mode)
        tab = self.tabs.get(mode)
        if tab is not None and self.inputs is not None:
            tab.on_show()
            self.fit_cameras(tab.planes())
        self.save()

    def fit_cameras(self, geoms: list[scene2d.PlaneGeometry]) -> None:
        """Point every client's camera (and the initial camera) at ``geoms``."""
        if not geoms:
            return
        self._fit_geoms = list(geoms)
        pose = scene2d.fit_camera(geoms)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up, cam.fov = (
            pose["position"],
            pose["look_at"],
            pose["up"],
            pose["fov"],
        )
        for client in self.server.get_clients().values():
            self._apply_camera(client, self._pose_for(client, geoms))

    @staticmethod
    def _pose_for(client, geoms) -> dict:
        # A portrait viewport's horizontal field is narrower than its vertical one: fit the width
        # through it. A landscape viewport keeps the square fit, because viser's control panel
        # covers part of the canvas's width and a tighter fit puts the image under it.
        w, h = client.camera.image_width, client.camera.image_height
        aspect = min(w / h, 1.0) if w and h else 1.0
        return scene2d.fit_camera(geoms, aspect=aspect)

    @staticmethod
    def _apply_camera(client, pose: dict) -> None:
        with client.atomic():
            client.camera.fov = pose["fov"]
            client.camera.up_direction = pose["up"]
            client.camera.position = pose["position"]
            client.camera.look_at = pose["look_at"]

    def _on_connect(self, client) -> None:
        self._fit_client(client)
        # The viewport's shape arrives with the client's camera messages: fit once more when it
        # is first known (later updates are the analyst panning and zooming: left alone).
        fitted: dict[str, bool] = {"done": False}

        def on_camera(_cam) -> None:
            if fitted["done"]:
                return
            if client.camera.image_width and client.camera.image_height:
                fitted["done"] = True
                self._fit_client(client)

        client.camera.on_update(on_camera)

    def _fit_client(self, client) -> None:
        tab = self.tabs.get(self.state.mode)
        if tab is not None and self.inputs is not None:
            geoms = tab.planes()
            if geoms:
                self._apply_camera(client, self._pose_for(client, geoms))

    def _on_scene_click(self, event) -> None:
        self.handle_click(event.ray_origin, event.ray_direction, event.client)

    def handle_click(self, origin, direction, client=None) -> tuple[str, np.ndarray] | None:
        """Route a click ray to the current view: ``(plane name, pixel)`` it hit, or None."""
        with self.state.lock:
            mode = self.state.mode
        tab = self.tabs.get(mode)
        if tab is None or self.inputs is None:
            return None
        for name, geom in tab.clickable().items():
            xy = geom.pixel_from_ray(origin, direction)
            if xy is not None and geom.contains(xy):
                tab.on_click(name, xy, client)
                return name, xy
        return None

    # ------------------------------------------------------------------ feedback
    def set_status(self, text: str) -> None:
        if hasattr(self, "status"):
            self.status.content = text

    def set_progress(self, percent: float | None) -> None:
        if percent is None:
            self.progress.visible = False
            return
        self.progress.visible = True
        self.progress.value = float(np.clip(percent, 0.0, 100.0))

    def notify(self, client, title: str, body: str, *, color: str = "blue") -> None:
        """A notification to one client, or to all when ``client`` is None (Python-side calls)."""
        self.notices.append((title, body, color))
        del self.notices[:-50]
        if color == "red":
            self._remember_error(f"{title}: {body}")
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            try:
                c.add_notification(
                    title, body, color=color, auto_close_seconds=8.0, with_close_button=True
                )
            except Exception:  # a client that just disconnected
                log.debug("notification to a gone client dropped", exc_info=True)

    def _remember_error(self, message: str) -> None:
        log.warning("%s", message)
        self.errors.append(message)
        del self.errors[:-20]

    def _report_error(self, key: str, exc: BaseException) -> None:
        self.notify(None, f"{key} failed", f"{type(exc).__name__}: {exc}", color="red")

    # ------------------------------------------------------------------ persistence
    def save(self) -> None:
        """Write the session to project.json atomically (call after every decision)."""
        with self.state.lock:
            session = self.state.to_session()
            self.project.save(session)

    def stop(self) -> None:
        """Cancel the running job, stop timers and the worker, then the server."""
        self.jobs.request_cancel()
        self.jobs.join(30)
        for tab in self.tabs.values():
            tab.shutdown()
        self.worker.stop()
        self.worker.join(10)
        self.server.stop()


def _size(n: float) -> str:
    """Human-readable byte count (B, kB, MB, GB; 1 kB = 1024 B)."""
    if n < 1024:
        return f"{n:.0f} B"
    for unit, k in (("kB", 1), ("MB", 2), ("GB", 3)):
        if n < 1024 ** (k + 1) or unit == "GB":
            return f"{n / 1024**k:.1f} {unit}"
    raise AssertionError("unreachable")


def bound_address(host: str, port: int) -> str:
    """What the server listens on, as printed at start: the address actually bound, and for a
    wildcard bind which URL to open on this machine."""
    if host in ("0.0.0.0", "", "::"):
        shown = "[::]" if host == "::" else "0.0.0.0"
        return (
            f"listening on all interfaces ({shown}:{port}); open http://127.0.0.1:{port} here "
            f"or http://<this machine's address>:{port} from another machine"
        )
    name = f"[{host}]" if ":" in host else host
    return f"serving http://{name}:{port}"


def serve(
    *,
    frames: str | None,
    base: str | None,
    project_dir: str | None,
    host: str = "127.0.0.1",
    port: int = 8080,
    allow_dirs: list[str] | None = None,
    max_upload_mb: float = 500.0,
    ready: Callable[[App], None] | None = None,
    block: bool = True,
) -> App:
    """Start the app; prints the URL on stderr. Blocks until Ctrl-C when ``block``."""
    for name, p in (("--frames", frames), ("--base", base)):
        if p and not any(ch in p for ch in "*?[") and not Path(p).exists():
            raise FileNotFoundError(f"{name} not found: {p}")
    if (frames is None) != (base is None):
        raise ValueError("--frames and --base go together (or give neither for the built-in demo)")
    for p in allow_dirs or []:
        if not Path(p).is_dir():
            raise FileNotFoundError(f"--allow-dir is not a folder: {p}")
    folder = Path(project_dir) if project_dir else default_project_dir(frames, base)
    project = Project(folder)
    # The current folder is not allowed implicitly: the browser may open only what was named.
    allowed = [project.folder]
    for p in (frames, base):
        if p:
            allowed.append(Path(p).expanduser().resolve().parent)
    allowed += [Path(p) for p in allow_dirs or []]
    # viser prints its own banner on stdout; keep stdout for machine-readable output.
    with contextlib.redirect_stdout(sys.stderr):
        server = security.make_server(host=host, port=port, verbose=False)
    app = App(
        server,
        project,
        frames=frames,
        base=base,
        allowed_dirs=allowed,
        max_upload_mb=max_upload_mb,
        project_is_explicit=project_dir is not None,
    )
    try:
        app.start()
    except BaseException:
        app.stop()
        raise
    sys.stderr.write(
        f"aerialreg app: {bound_address(host, server.get_port())}  (project {project.folder})\n"
    )
    sys.stderr.flush()
    if ready is not None:
        ready(app)
    if block:
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
        finally:
            app.stop()
    return app
