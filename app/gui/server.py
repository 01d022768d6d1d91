"""The analyst's browser app (viser): γ calibration, seeding, match and control-point review,
the registered sequence, Table 2.

Structure (``notes/viser.md``, ``notes/style.md`` practice 12):

* :class:`App` implements the views' :class:`~app.gui.context.ViewContext` (views never import
  this module). It owns the viser server, the one :class:`~app.gui.state.AppState` (one lock), the
  project folder, one :class:`~app.gui.worker.LatestWorker` for interactive renders (latest request
  wins) and one :class:`~app.gui.worker.JobRunner` for long runs (demo build, fits, registration),
  whose progress and time left show in the header.
* The header: the step checklist (calibrated → seeded → reference registered → sequence
  registered → evaluated) with what to do next, the view buttons (the active one marked), the
  running job with a Cancel button.
* One view per step (``app/gui/views/<view>/``): each split into its panel (widgets), its scene
  (drawing) and the view (state and actions). Shared results live in the state, not in the views.
* GUI callbacks only update state and post requests; scene drawing and anything slower than a
  frame happen on the worker or as a job. Nothing touches the disk while the state's lock is held
  (the session is copied under it and written after).
* Clicks on the scene arrive as rays; :meth:`App.handle_click` intersects them with the current
  view's image planes and hands pixel coordinates to the view. The browser's zoom is followed so
  markers keep their size on screen.
* Security (``app/gui/security.py``): paths checked against allowed folders, handshakes checked,
  share tunnel refused, uploads limited while they arrive and kept in the project.

Nothing here computes registration results: every number and image comes from ``registration``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from app.gui import assets, scene2d, security
from app.gui.context import Client
from app.gui.header import HeaderPanel, InputsPanel
from app.gui.inputs import Inputs
from app.gui.messages import browser_message
from app.gui.project import Project, default_project_dir, input_identity, upload_name
from app.gui.security import escape_md, resolve_allowed
from app.gui.state import MODES, AppState
from app.gui.views.calibrate.view import CalibrateView
from app.gui.views.evaluate.view import EvaluateView
from app.gui.views.seed.view import SeedView
from app.gui.views.sequence.view import SequenceView
from app.gui.views.traffic.view import TrafficView
from app.gui.worker import Job, JobRunner, LatestWorker
from app.progress import human_size

log = logging.getLogger(__name__)

VIEWS = (CalibrateView, SeedView, SequenceView, EvaluateView, TrafficView)
"""The views, in the order of the analyst's work (and of :data:`app.gui.state.MODES`)."""
PANEL_WIDTH_PX = 480
ZOOM_STEP = 0.1
SAVE_DELAY_S = 0.5
"""Relative zoom change after which screen-sized markers are redrawn."""


class App:
    """The running app. Construct, then :meth:`start`; :meth:`stop` ends it.

    Args:
        server: a viser server (the caller chooses host/port; ``security.make_server`` checks
            handshakes).
        project: the project folder.
        frames, base: input paths; None for both = the saved inputs or the built-in demo.
        allowed_dirs: folders the browser's path field may open from (the project is added).
        max_upload_mb: uploads larger than this are refused while they arrive.
        max_download_mb: files (and zipped exports) larger than this are not sent to the browser
            (they are in the project folder); the whole file is held in memory while sent.
        display_max: longest side in pixels of images sent to the browser for frames;
            the base map is sent at up to twice that.
        demo_builder: returns the demo folder (frames/, base.png); default
            ``registration.synth.demo_sequence``; tests inject a small one.
        project_is_explicit: False when the project was chosen for the inputs (then other
            inputs open their own project).
        data_dir: where per-input projects live (default: the user's data folder).
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
        max_download_mb: float = 1024.0,
        display_max: int = 1024,
        demo_builder: Callable[..., Path] | None = None,
        project_is_explicit: bool = True,
        data_dir: Path | None = None,
        auto_gamma: bool = False,
    ) -> None:
        self.server = server
        # Frames opened while no γ was ever set start the estimate from their motion, and a
        # determined one becomes γ, as `aerialreg register`'s default --gamma auto does.
        self.auto_gamma = auto_gamma
        self.project = project
        self.project_is_explicit = project_is_explicit
        self.data_dir = data_dir
        self.state = AppState()
        self.worker = LatestWorker(on_error=self._report_error)
        self.jobs = JobRunner(
            on_error=self._report_error,
            on_progress=self._job_progress,
            on_finish=self._job_finished,
            on_start=self._job_started,
        )
        self.max_upload_bytes = int(max_upload_mb * 1024 * 1024)
        self.max_download_bytes = int(max_download_mb * 1024 * 1024)
        self.display_max = int(display_max)
        self.allowed_dirs = [Path(p).expanduser().resolve() for p in (allowed_dirs or [])]
        self.inputs: Inputs | None = None
        self.demo_builder = demo_builder
        self.shown: dict[str, Any] = {}  # what each view last handed to viser (tests, bench)
        self._cli_inputs = (frames, base)
        self.views: dict[str, Any] = {}
        self.errors: list[str] = []  # last error messages (tests read them)
        self.notices: list[tuple[str, str, str]] = []  # last notifications (title, body, colour)
        self._uploaded: dict[str, str] = {}  # this sitting's uploads not yet opened: kind -> path
        self._zoom_applied: float | None = None
        self._last_progress = 0.0
        self._save_lock = threading.Lock()
        self._save_timer: threading.Timer | None = None
        self._write_lock = threading.Lock()  # one project.json write at a time
        self._snapshots = 0  # sessions copied for saving so far (under the state's lock)
        self._written = 0  # the newest of them written

    # ------------------------------------------------------------------ the views' context
    @property
    def scene(self) -> viser.SceneApi:
        return self.server.scene

    @property
    def gui(self) -> viser.GuiApi:
        return self.server.gui

    def atomic(self):
        return self.server.atomic()

    def gui_for(self, client: Client) -> viser.GuiApi:
        return client.gui if client is not None else self.server.gui

    def camera_position(self, client: Client) -> tuple[float, float, float]:
        cam = client.camera if client is not None else self.server.initial_camera
        return tuple(cam.position)

    def submit(self, key: str, fn: Callable[[], None]) -> None:
        self.worker.submit(key, fn)

    # ------------------------------------------------------------------ setup
    def start(self) -> None:
        server = self.server
        server.gui.configure_theme(
            control_width="large", show_share_button=False, show_logo=False, dark_mode=False
        )
        # Hiding the share button is not enough: any client can still ask for the tunnel.
        security.refuse_share_tunnel(server)
        security.install_upload_limit(server, self.max_upload_bytes, self._upload_refused)
        # Dock the panel beside the canvas so it never covers the images; wide enough for the
        # control-point table's ten columns.
        server.gui.main_panel.dock_right()
        server.gui.main_panel.set_width(PANEL_WIDTH_PX)
        server.initial_camera.position = (0.0, 0.0, -2.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, -1.0, 0.0)
        self.events = assets.EventChannel(server.gui)
        assets.install(server, self.events)

        try:
            session = self.project.load()
        except ValueError as exc:
            self.record_error(str(exc))
            session = {}
        with self.state.lock:
            self.state.apply_session(session)

        self._build_header()
        self._build_inputs_folder()
        for cls in VIEWS:
            view = cls(self)
            self.views[view.MODE] = view
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
                self.record_error(f"could not reopen saved inputs: {exc}")
                self._start_demo()
        else:
            self._start_demo()
        self.set_mode(self.state.mode)

    def _build_header(self) -> None:
        self.header = HeaderPanel(self.server.gui)
        self.header.on_view_chosen(lambda mode, client: self.set_mode(mode))
        self.header.on_cancel(lambda client: self.jobs.request_cancel())

    def _build_inputs_folder(self) -> None:
        self.inputs_panel = InputsPanel(self.server.gui)
        self.inputs_panel.on_open(self.open_paths_from_gui)
        self.inputs_panel.on_upload(self.handle_upload)
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
        self.inputs_panel.show_info(
            f"Project: {escape_md(self.project.folder)}  \nPaths may lie under: {allowed}  \n"
            f"Uploads up to {human_size(self.max_upload_bytes)}; upload both inputs, or one and "
            "press *Open paths*."
        )

    # ------------------------------------------------------------------ header
    def update_header(self) -> None:
        """View buttons (active ▶, done ✓), the checklist and what comes next."""
        with self.state.lock:
            steps = self.state.steps()
            mode = self.state.mode
            stale = self.state.result_staleness()
        self.header.show_steps(steps, mode, stale)

    def state_changed(self) -> None:
        """Shared state changed: refresh the header and every view's texts."""
        self.update_header()
        for view in self.views.values():
            try:
                view.on_state_changed()
            except Exception:
                log.exception("refreshing %s failed", view.MODE)

    def run_job(
        self, name: str, fn: Callable[[Job], None], client=None, *, queue: bool = False
    ) -> bool:
        """Run ``fn(job)`` as the app's long job (progress in the header); a notification when
        another job is running (unless ``queue``: then it runs after it)."""
        started = self.jobs.start(name, fn, queue=queue)
        if not started:
            self.notify(client, "Busy", f"{self.jobs.name} is running", color="yellow")
        return started

    def _job_started(self, job: Job) -> None:
        self.header.show_job(f"{job.name} ...")

    def _job_progress(self, job: Job) -> None:
        now = time.monotonic()
        if now - self._last_progress < 0.25 and job.total and job.done < job.total:
            return
        self._last_progress = now
        self.header.show_job_progress(escape_md(job.describe()))
        frac = job.fraction
        if frac is not None:
            self.set_progress(100.0 * frac)

    def _job_finished(self, job: Job) -> None:
        if self.jobs.job is job:
            self.header.show_job(None)
            self.set_progress(None)

    # ------------------------------------------------------------------ inputs
    def _start_demo(self) -> None:
        self.set_status("Building the built-in demo sequence (first use only) ...")

        def build(job: Job) -> None:
            builder = self.demo_builder
            if builder is None:
                from registration.synth import demo_sequence as builder
            from app.progress import ProgressBar

            bar_holder: dict[str, ProgressBar] = {}

            def progress(done: int, total: int) -> None:
                # registration.synth's progress protocol: (steps done, total steps).
                job(done, total, "demo steps")
                if "bar" not in bar_holder:
                    bar_holder["bar"] = ProgressBar(total, "demo").__enter__()
                bar = bar_holder["bar"]
                bar.update(done - bar.done)

            folder = Path(builder(progress=progress))
            if "bar" in bar_holder:
                bar_holder["bar"].__exit__(None, None, None)
            self.open_inputs(str(folder / "frames"), str(folder / "base.png"), client=None)
            self.set_mode(self.state.mode)

        self.run_job("demo", build)

    def open_paths_from_gui(self, client: Client) -> None:
        """The "Open paths" button: check both paths against the allowed folders, then open."""
        frames_text, base_text = self.inputs_panel.paths
        try:
            frames = resolve_allowed(frames_text, self.allowed_roots())
            base = resolve_allowed(base_text, self.allowed_roots())
        except (ValueError, FileNotFoundError) as exc:
            self.notify(client, "Path refused", str(exc), color="red")
            return
        self.worker.submit("open", lambda: self._open_and_report(str(frames), str(base), client))

    def _open_and_report(self, frames: str, base: str, client) -> None:
        try:
            self.open_inputs(frames, base, client=client)
        except (OSError, ValueError, IndexError) as exc:
            self.notify(client, "Could not open inputs", browser_message(exc), color="red")
            return
        self.set_mode(self.state.mode)
        self.notify(client, "Inputs opened", f"{frames}\n{base}", color="green")

    def _upload_refused(self, client_id: int, name: str, size: int) -> None:
        """The upload guard refused a transfer while it arrived (security.install_upload_limit)."""
        client = self.server.get_clients().get(client_id)
        self.notify(
            client,
            "Upload refused",
            f"{name} is {human_size(size)}; the limit is {human_size(self.max_upload_bytes)} (--max-upload-mb)",
            color="red",
        )

    def handle_upload(self, kind: str, uploaded, client) -> None:
        """Save an uploaded file in the project (size-checked), then open it together with the
        other input once both were uploaded; an upload alone waits for *Open paths* (so that an
        unfinished pair never creates a project)."""
        name = Path(getattr(uploaded, "name", "") or "upload").name
        content = getattr(uploaded, "content", b"") or b""
        if len(content) > self.max_upload_bytes:
            self.notify(
                client,
                "Upload refused",
                f"{name} is {human_size(len(content))}; the limit is "
                f"{human_size(self.max_upload_bytes)} (--max-upload-mb)",
                color="red",
            )
            return
        if not content:
            self.notify(client, "Upload refused", f"{name} is empty", color="red")
            return
        path = self.project.write_file(f"uploads/{upload_name(kind, name, content)}", content)
        self._uploaded[kind] = str(path)
        self.inputs_panel.show_path(kind, str(path))
        if "frames" in self._uploaded and "base" in self._uploaded:
            frames, base = self._uploaded["frames"], self._uploaded["base"]
            self.worker.submit("open", lambda: self._open_and_report(frames, base, client))
            return
        other = "base map" if kind == "frames" else "frames"
        self.notify(
            client,
            "Uploaded",
            f"{name} saved. Upload the {other} too, or press Open paths to use it with the "
            f"{other} in its box.",
            color="blue",
        )

    def _project_for(self, frames: str, base: str) -> tuple[str, str]:
        """Switch to the inputs' own project (unless one was given explicitly); uploads move
        with them. Returns the inputs' paths (moved uploads have new ones)."""
        with self.state.lock:
            current = (self.state.frames_path, self.state.base_path)
        if self.project_is_explicit or current == (None, None):
            return frames, base
        ident = (input_identity(frames), input_identity(base))
        if ident == (input_identity(current[0]), input_identity(current[1])):
            return frames, base
        folder = default_project_dir(frames, base, self.data_dir)
        if Path(folder).resolve() == self.project.folder:
            return frames, base
        old = self.project
        new = Project(folder)
        frames, base = new.adopt_upload(frames), new.adopt_upload(base)
        self.project = new
        try:
            session = new.load()
        except ValueError as exc:
            self.record_error(str(exc))
            session = {}
        # The project left behind keeps only the uploads its own session uses.
        try:
            old_session = old.load()
            old.prune_uploads(
                [old_session.get("frames_path") or "", old_session.get("base_path") or ""]
            )
        except ValueError:
            pass
        with self.state.lock:
            mode = self.state.mode
            self.state.replace_session(session)
            self.state.mode = mode
            self.state.reference = self.state.result = self.state.report = None
        return frames, base

    def open_inputs(self, frames: str, base: str, client) -> None:
        """Open inputs (raises on unusable ones) and reset everything that depends on them."""
        inputs = Inputs(frames, base)
        frames, base = self._project_for(inputs.frames_path, inputs.base_path)
        if (frames, base) != (inputs.frames_path, inputs.base_path):
            inputs.close()
            inputs = Inputs(frames, base)
        self._uploaded.clear()
        with self.state.lock:
            st = self.state
            same = st.frames_path == inputs.frames_path and st.base_path == inputs.base_path
            if not same:
                st.lines, st.line_open = [], False
                st.seed_frame = st.seed_base = st.seed2_frame = st.seed2_base = None
                st.reference = st.result = st.report = None
                st.result_dir = None
                st.points, st.pending = {}, {}
                st.undo_stack.clear()
                st.calib_frame = st.seq_frame = st.eval_frame = st.reference_frame = 0
            st.frames_path, st.base_path = inputs.frames_path, inputs.base_path
            st.n_frames, st.frame_size, st.base_size = (
                inputs.n_frames,
                inputs.frame_size,
                inputs.base_size,
            )
            for name in ("calib_frame", "seq_frame", "eval_frame", "reference_frame"):
                setattr(st, name, int(np.clip(getattr(st, name), 0, inputs.n_frames - 1)))
            old, self.inputs = self.inputs, inputs
            st.revision += 1
        if old is not None:
            old.close()
        self.inputs_panel.show_path("frames", inputs.frames_path)
        self.inputs_panel.show_path("base", inputs.base_path)
        # Uploads no input refers to any more are removed (they can be hundreds of MB).
        self.project.prune_uploads([inputs.frames_path, inputs.base_path])
        self._update_inputs_md()
        for view in self.views.values():
            view.on_inputs()
        self.publish_planes()
        self.save()
        with self.state.lock:
            unset = not self.state.gamma_set
        if self.auto_gamma and unset and inputs.n_frames >= 2:
            self.views["Calibrate"].estimate_from_motion(client, as_default=True)
        self.set_status(
            f"**{escape_md(Path(inputs.frames_path).name)}**: {inputs.n_frames} frames "
            f"{inputs.frame_size[0]}x{inputs.frame_size[1]}; base "
            f"{inputs.base_size[0]}x{inputs.base_size[1]}"
        )
        self.state_changed()

    # ------------------------------------------------------------------ views and clicks
    def set_mode(self, mode: str) -> None:
        if mode not in MODES:
            return
        with self.state.lock:
            self.state.mode = mode
        for name, view in self.views.items():
            view.set_visible(name == mode)
        view = self.views.get(mode)
        if view is not None and self.inputs is not None:
            view.on_show()
            self.fit_cameras(view.fit_geoms())
            self._zoom_applied = None
        self.update_header()
        self.save()

    def publish_planes(self) -> None:
        """The images of every view, for the browser's pointer readout (which reads those of
        the view shown: the others' scene nodes are hidden). Sent when the inputs change, not
        on every view switch: each message stays in viser's buffer for later clients."""
        inp = self.inputs
        if inp is None:
            return
        georef = getattr(inp, "base_georef", None)
        planes = []
        for view in self.views.values():
            for name, plane in view.scene.planes.items():
                g = plane.geom
                entry = {
                    "node": plane.name,
                    "label": "map" if name == "base" else f"{name} (as drawn)",
                    "width": g.width,
                    "height": g.height,
                    "position": [float(v) for v in g.position],
                    "scale": float(g.scale),
                }
                if name == "base" and georef is not None:
                    epsg = georef.epsg
                    entry.update(
                        affine=list(georef.transform),
                        unit=georef.units or "",
                        crs=f"EPSG:{epsg}" if epsg else "",
                    )
                planes.append(entry)
        assets.publish_planes(self.server, planes)

    def fit_cameras(self, geoms: list[scene2d.PlaneGeometry]) -> None:
        """Point every client's camera (and the initial camera) at ``geoms``."""
        if not geoms:
            return
        pose = scene2d.fit_camera(geoms)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up, cam.fov = (
            pose["position"],
            pose["look_at"],
            pose["up"],
            pose["fov"],
        )
        for client in self.server.get_clients().values():
            self.apply_camera(client, self._pose_for(client, geoms))

    def focus(self, geoms: list[scene2d.PlaneGeometry], client=None) -> None:
        """Point one client's camera (all when None) at ``geoms`` (a fit or zoom to a point)."""
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            self.apply_camera(c, self._pose_for(c, geoms))

    @staticmethod
    def _pose_for(client, geoms) -> dict:
        # The control panel is docked beside the canvas (not over it), so the canvas's own shape
        # is what the images must fit.
        w, h = client.camera.image_width, client.camera.image_height
        aspect = w / h if w and h else 1.0
        return scene2d.fit_camera(geoms, aspect=aspect)

    @staticmethod
    def apply_camera(client, pose: dict) -> None:
        with client.atomic():
            client.camera.fov = pose["fov"]
            client.camera.up_direction = pose["up"]
            client.camera.position = pose["position"]
            client.camera.look_at = pose["look_at"]

    def _on_connect(self, client) -> None:
        self._fit_client(client)
        # The viewport's shape arrives with the client's camera messages: fit once more when it
        # is first known (later updates are the analyst panning and zooming: they only resize
        # the screen-sized markers).
        fitted: dict[str, bool] = {"done": False}

        def on_camera(cam) -> None:
            if not fitted["done"] and cam.image_width and cam.image_height:
                fitted["done"] = True
                self._fit_client(client)
            self.camera_moved(float(cam.position[2]), float(cam.fov), int(cam.image_height or 0))

        client.camera.on_update(on_camera)

    def camera_moved(self, camera_z: float, fov: float, viewport_height: int) -> None:
        """A browser's camera moved: resize screen-sized markers when the zoom changed enough."""
        if viewport_height <= 0:
            return
        zoom = scene2d.world_per_screen_px(camera_z, fov, viewport_height)
        with self.state.lock:
            self.state.zoom = zoom
        last = self._zoom_applied
        if last is not None and abs(zoom / last - 1.0) < ZOOM_STEP:
            return
        self._zoom_applied = zoom
        self.worker.submit("zoom", self._apply_zoom)

    def _apply_zoom(self) -> None:
        with self.state.lock:
            zoom, mode = self.state.zoom, self.state.mode
        view = self.views.get(mode)
        if zoom is not None and view is not None:
            with self.server.atomic():
                view.scene.set_zoom(zoom)

    def _fit_client(self, client) -> None:
        view = self.views.get(self.state.mode)
        if view is not None and self.inputs is not None:
            geoms = view.fit_geoms()
            if geoms:
                self.apply_camera(client, self._pose_for(client, geoms))

    def _on_scene_click(self, event) -> None:
        self.handle_click(event.ray_origin, event.ray_direction, event.client)

    def handle_click(self, origin, direction, client=None) -> tuple[str, np.ndarray] | None:
        """Route a click ray to the current view: ``(plane name, pixel)`` it hit, or None."""
        with self.state.lock:
            mode = self.state.mode
        view = self.views.get(mode)
        if view is None or self.inputs is None:
            return None
        hit = view.scene.plane_at(origin, direction)
        if hit is None or hit[0] not in view.CLICKABLE:
            return None
        view.on_click(hit[0], hit[1], client)
        return hit

    # ------------------------------------------------------------------ feedback
    def set_status(self, text: str) -> None:
        if hasattr(self, "header"):
            self.header.show_status(text)

    def set_progress(self, percent: float | None) -> None:
        self.header.show_progress(None if percent is None else float(np.clip(percent, 0.0, 100.0)))

    def notify(self, client, title: str, body: str, *, color: str = "blue") -> None:
        """A notification to one client, or to all when ``client`` is None (Python-side calls)."""
        self.notices.append((title, body, color))
        del self.notices[:-50]
        if color == "red":
            self.record_error(f"{title}: {body}")
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            try:
                c.add_notification(
                    title, body, color=color, auto_close_seconds=8.0, with_close_button=True
                )
            except Exception:  # a client that just disconnected
                log.debug("notification to a gone client dropped", exc_info=True)

    def send_download(self, client, name: str, data: bytes) -> None:
        """Send a file to the browser that asked (all when None) and save it there at once."""
        target = client if client is not None else self.server
        target.send_file_download(name, data, save_immediately=True)

    def offer_file(self, path: Path, client=None, *, name: str | None = None) -> bool:
        """Send a file the app wrote into the project to the browser (saved there at once) and
        say where it is; files over the download limit stay on disk only (the notice says so)."""
        path = Path(path)
        size = path.stat().st_size
        where = str(path)
        if size > self.max_download_bytes:
            self.notify(
                client,
                f"{path.name} saved",
                f"{where} ({human_size(size)}) is over the download limit "
                f"({human_size(self.max_download_bytes)}): copy it from the project folder",
                color="yellow",
            )
            return False
        self.send_download(client, name or path.name, path.read_bytes())
        self.notify(client, name or path.name, f"saved to {where} and sent", color="green")
        return True

    def record_error(self, message: str) -> None:
        """Log an error and keep it for tests and the benchmark (the last 20)."""
        log.warning("%s", message)
        self.errors.append(message)
        del self.errors[:-20]

    def _report_error(self, key: str, exc: BaseException) -> None:
        self.notify(None, f"{key} failed", browser_message(exc), color="red")

    # ------------------------------------------------------------------ persistence
    def save(self, *, soon: bool = False) -> None:
        """Write the session to project.json atomically (call after every decision).

        ``soon``: within :data:`SAVE_DELAY_S`, once for a burst of calls (the scrubber's frame
        changes; each write is fsync'ed, which costs more than drawing a frame)."""
        if soon:
            with self._save_lock:
                if self._save_timer is None:
                    self._save_timer = threading.Timer(SAVE_DELAY_S, self._save_now)
                    self._save_timer.daemon = True
                    self._save_timer.start()
            return
        self._save_now()

    def _save_now(self) -> None:
        with self._save_lock:
            if self._save_timer is not None:
                self._save_timer.cancel()
                self._save_timer = None
        # Copied under the state's lock, written (and fsync'ed) after it: callbacks and the
        # worker never wait for the disk. Writes are serialised by their own lock, and a copy
        # older than one already written is dropped, so the file always ends with the newest.
        with self.state.lock:
            session = self.state.to_session()
            self._snapshots += 1
            snapshot = self._snapshots
        with self._write_lock:
            if snapshot < self._written:
                return
            self.project.save(session)
            self._written = snapshot

    def stop(self) -> None:
        """Cancel the running job, stop timers and the worker, then the server."""
        with self._save_lock:
            pending = self._save_timer is not None
        if pending:
            self._save_now()
        self.jobs.request_cancel()
        self.jobs.join(30)
        for view in self.views.values():
            view.shutdown()
        self.worker.stop()
        self.worker.join(10)
        if self.inputs is not None:
            self.inputs.close()
        self.server.stop()
