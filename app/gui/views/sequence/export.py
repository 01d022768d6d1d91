"""Export of the registration result from the Sequence view (``registration.gis.export``).

The analyst ticks formats (GeoTIFF or cloud-optimised GeoTIFF frames, PNG frames with world
files, the mosaic, the registered video, QGIS ``.points``, transforms JSON, GeoJSON or GeoPackage
of control points, footprints and the evaluation marks) and presses *Export*: one call of
:func:`registration.gis.export.export_result` runs as the app's job, with its progress, time left
and Cancel in the header. Files go to the project's ``exports/`` folder; files that exist are
never replaced without asking (a dialog offers to overwrite them or to write into a new numbered
folder ``exports-2``, ``exports-3``, ...). Written files are listed and can be downloaded (one
file as is, several as a zip). Formats that need map coordinates are disabled, with the reason,
when the base map has no georeference.
"""

from __future__ import annotations

import copy
import io
import logging
import threading
import time
import zipfile
from pathlib import Path

from app.gui.context import Client, ViewContext
from app.gui.messages import browser_message
from app.gui.security import escape_md
from app.gui.views.sequence.export_panel import TRAFFIC, ExportPanel
from app.progress import human_size as _size

EXPORT_DIR = "exports"
log = logging.getLogger(__name__)
NO_GEOREF = (
    "GeoTIFF, COG, mosaic, .points, GeoJSON and GeoPackage need map coordinates: this base map "
    "has no georeference (open a GeoTIFF, or a PNG/JPEG with a world file)."
)
STORED = (".tif", ".png", ".mp4", ".gpkg", ".jpg")
"""Already compressed: stored in a download zip as they are."""


class Exporter:
    """The export's actions (the Sequence view owns one)."""

    def __init__(self, ctx: ViewContext, panel: ExportPanel) -> None:
        self.ctx = ctx
        self.state = ctx.state
        self.panel = panel
        self.written: dict[str, list[Path]] = {}
        self.format_of_label: dict[str, str] = {}  # the download list's entries -> format
        self.out_dir: Path | None = None
        self.summary: dict | None = None
        self.modal = None
        self._pending: tuple | None = None  # a request waiting for the overwrite answer
        self._lock = threading.Lock()
        panel.on_export(self.request)
        panel.on_download(self.download)

    # ------------------------------------------------------------------ texts
    def georef(self):
        """The georeference of the result's base: recorded in the result, else the open base's."""
        with self.state.lock:
            r = self.state.result
        inp = self.ctx.inputs
        if r is not None and r.georef is not None:
            return r.georef
        return None if inp is None else inp.base_georef

    def refresh(self) -> None:
        """Availability of formats (georeference, a result) and the target folder."""
        from registration.gis import MAP_FORMATS

        with self.state.lock:
            r = self.state.result
        georef = self.georef()
        ok = r is not None and any(r.is_ok(k) for k in range(r.n_frames))
        unavailable = set(MAP_FORMATS) if georef is None else set()
        if not self.traffic_files():
            unavailable.add(TRAFFIC)
        self.panel.show_availability(unavailable, ok)
        self.panel.show_georef(
            f"_{NO_GEOREF}_"
            if georef is None
            else f"Map coordinates: {escape_md(_crs_name(georef))}, "
            f"{georef.pixel_size[0]:.3g} {escape_md(georef.units or 'units')} per map pixel."
        )
        where = escape_md(self.ctx.project.folder / EXPORT_DIR)
        self.panel.show_intro(
            f"Into {where} (existing files are never replaced without asking)."
            if ok
            else "_Register the sequence first: exports are made from its result._"
        )

    # ------------------------------------------------------------------ exporting
    def options(self, force: bool = False):
        from registration.gis import ExportOptions

        c = self.panel.choices()
        return ExportOptions(
            stage=c.stage,
            mosaic=c.mosaic,
            fps=c.fps,
            video_scale=c.video_scale,
            vector_crs=c.vector_crs,
            force=force,
        )

    def marks(self):
        """The confirmed evaluation marks as ``registration.evaluation.points.PointMarks`` (None when
        there are none or they are not wanted)."""
        from registration.evaluation import PointMarks

        if not self.panel.choices().marks:
            return None
        with self.state.lock:
            marks = self.state.confirmed_marks()
        marks = {p: m for p, m in marks.items() if m}
        if not marks:
            return None
        return PointMarks(marks=marks, order=sorted(marks), source="app")

    def traffic_files(self) -> list[Path]:
        """The files of the Traffic view's run of the open result (its own outputs and the
        road sections' counts); none when there is no run, or it was made from another
        result."""
        import json

        with self.state.lock:
            run, result = self.state.traffic, self.state.result
        if run is None or result is None:
            return []
        try:
            identity = json.loads((run.out / "traffic.json").read_text())
        except (OSError, ValueError):
            return []
        if identity.get("result") != str(Path(result.out_dir).resolve()):
            return []
        names = [*run.summary.get("files", []), "counts.csv", "crossings.csv"]
        return [run.out / n for n in names if (run.out / n).is_file()]

    def target(self, result, formats, marks, folder: Path) -> list[Path]:
        """The files of ``formats`` that already exist in ``folder``."""
        from registration.gis import planned_files, resolve_formats

        files = (
            [folder / TRAFFIC / p.name for p in self.traffic_files()] if TRAFFIC in formats else []
        )
        formats = [f for f in formats if f != TRAFFIC]
        if formats:
            planned = copy.copy(result)
            planned.georef = self.georef()
            files += planned_files(planned, folder, resolve_formats(formats), marks)
        return [f for f in files if f.exists()]

    def next_free_folder(self) -> Path:
        """``exports-2``, ``exports-3``, ...: the first that does not exist."""
        n = 2
        while (self.ctx.project.folder / f"{EXPORT_DIR}-{n}").exists():
            n += 1
        return self.ctx.project.folder / f"{EXPORT_DIR}-{n}"

    def request(self, client: Client = None, *, formats=None, answer: str | None = None) -> bool:
        """Export ``formats`` (default: the ticked ones) into ``exports/``.

        When files would be replaced, asks first (a dialog; ``answer`` = ``"overwrite"``,
        ``"new folder"`` or ``"cancel"`` answers it from Python). Returns whether the export job
        started."""
        with self.state.lock:
            r = self.state.result
        formats = list(formats) if formats is not None else self.panel.chosen()
        if r is None:
            self.ctx.notify(client, "Nothing to export", "Register the sequence first", "yellow")
            return False
        if not formats:
            self.ctx.notify(client, "Nothing to export", "Tick at least one format", "yellow")
            return False
        marks = self.marks()
        folder = self.ctx.project.folder / EXPORT_DIR
        try:
            existing = self.target(r, formats, marks, folder)
        except ValueError as exc:
            self.show_error(browser_message(exc), client)
            return False
        force = False
        if existing:
            if answer is None:
                with self._lock:
                    self._pending = (formats, client)
                self.ask(existing, folder, client)
                return False
            if answer == "overwrite":
                force = True
            elif answer == "new folder":
                folder = self.next_free_folder()
            else:
                return False
        return self.start(r, formats, marks, folder, force, client)

    def ask(self, existing: list[Path], folder: Path, client: Client) -> None:
        """The overwrite dialog (to the browser that asked, or to all)."""
        self.close_modal()
        self.modal = self.panel.ask_overwrite(
            self.ctx.gui_for(client), existing, folder, self.next_free_folder().name, self.answer
        )

    def close_modal(self) -> None:
        if self.modal is not None:
            try:
                self.modal.close()
            except Exception:  # the client that saw it is gone
                pass
            self.modal = None

    def answer(self, answer: str) -> bool:
        """The overwrite dialog's answer for the waiting request."""
        self.close_modal()
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is None:
            return False
        formats, client = pending
        return self.request(client, formats=formats, answer=answer)

    def start(self, result, formats, marks, folder: Path, force: bool, client) -> bool:
        from registration.gis import export_result
        from registration.io import frames as io_frames

        options = self.options(force)
        inp = self.ctx.inputs
        georef = self.georef()

        traffic = self.traffic_files() if TRAFFIC in formats else []
        formats = [f for f in formats if f != TRAFFIC]

        def job(progress) -> None:
            t0 = time.perf_counter()
            progress(0, None, "starting")
            summary = {"files": {}, "time_s": {}, "cancelled": False, "n_failed": 0}
            try:
                if formats:
                    # Its own decoder: the export reads every frame in order, the views seek.
                    frames = io_frames.open_frames(inp.frames_path) if inp is not None else None
                    summary = export_result(
                        result,
                        folder,
                        formats,
                        frames=frames,
                        georef=georef if result.georef is None else None,
                        marks=marks,
                        options=options,
                        progress=lambda done, total: progress(done, total, "steps"),
                        cancel=progress.cancel,
                    )
                if traffic and not summary["cancelled"]:
                    t1 = time.perf_counter()
                    summary["files"][TRAFFIC] = copy_traffic(traffic, folder / TRAFFIC, force)
                    summary["time_s"][TRAFFIC] = time.perf_counter() - t1
            except Exception as exc:  # the library's one-line reasons; a bug said as such
                self.show_error(browser_message(exc), client)
                return
            self.finished(summary, folder, time.perf_counter() - t0, client)

        # Shown before the job starts: a job that fails at once must not have its reason
        # overwritten by this line.
        previous = self.panel.result_text
        self.panel.result_text = f"_Exporting {', '.join(formats)} ..._"
        started = self.ctx.run_job("export", job, client)
        if not started:
            self.panel.result_text = previous
        return started

    def show_error(self, message: str, client) -> None:
        self.panel.result_text = f"**Export failed:** {escape_md(message)}"
        self.ctx.notify(client, "Export failed", message, color="red")

    def finished(self, summary: dict, folder: Path, seconds: float, client) -> None:
        files = {f: [Path(p) for p in ps] for f, ps in summary["files"].items() if ps}
        labels = {self.download_label(f, ps): f for f, ps in files.items()}
        with self._lock:
            self.written, self.out_dir, self.summary = files, folder, summary
            self.format_of_label = labels
        rows = ["| format | files | size | time |", "|---|---:|---:|---:|"]
        for f, ps in files.items():
            size = sum(p.stat().st_size for p in ps if p.exists())
            t = summary["time_s"].get(f)
            rows.append(
                f"| {f} | {len(ps)} | {_size(size)} | {'' if t is None else f'{t:.1f} s'} |"
            )
        state = "cancelled; the files written so far are kept" if summary["cancelled"] else "done"
        failed = summary.get("n_failed") or 0
        note = f" {failed} failed frame(s) left out (black in the video)." if failed else ""
        self.panel.result_text = (
            f"Export {state} in {seconds:.1f} s into {escape_md(folder)}.{note}\n\n"
            + ("\n".join(rows) if files else "_No file written._")
        )
        self.panel.offer_downloads(tuple(labels))
        title = "Export cancelled" if summary["cancelled"] else "Export finished"
        n = sum(len(ps) for ps in files.values())
        self.ctx.notify(
            client,
            title,
            f"{n} files in {folder}",
            color="yellow" if summary["cancelled"] else "green",
        )

    # ------------------------------------------------------------------ downloads
    @staticmethod
    def download_label(fmt: str, ps: list[Path]) -> str:
        """The download list's entry for the files ``ps`` of format ``fmt``."""
        size = _size(sum(p.stat().st_size for p in ps if p.exists()))
        if len(ps) == 1:
            return f"{fmt}: {ps[0].name} ({size})"
        return f"{fmt}: {len(ps)} files as zip ({size})"

    def download(self, label: str, client: Client = None) -> bool:
        """Send the exported files of the picked entry (:meth:`download_label`): one file as is,
        several as a zip."""
        with self._lock:
            fmt = self.format_of_label.get(label, "")
            paths, folder = list(self.written.get(fmt, [])), self.out_dir
        paths = [p for p in paths if p.exists()]
        if not paths or folder is None:
            self.ctx.notify(client, "Nothing to download", "Export first", "yellow")
            return False
        if len(paths) == 1:
            return self.ctx.offer_file(paths[0], client)
        size = sum(p.stat().st_size for p in paths)
        name = f"{folder.name}_{fmt}.zip"
        if size > self.ctx.max_download_bytes:
            self.ctx.notify(
                client,
                f"{fmt}: {len(paths)} files saved",
                f"{_size(size)} is over the download limit: copy them from {folder}",
                color="yellow",
            )
            return False
        self.ctx.submit("export-download", lambda: self._send_zip(name, folder, paths, client))
        return True

    def _send_zip(self, name: str, folder: Path, paths: list[Path], client) -> None:
        self.ctx.send_download(client, name, zip_files(folder, paths))
        self.ctx.notify(client, name, f"{len(paths)} files from {folder} sent", color="green")


def copy_traffic(paths: list[Path], out: Path, force: bool) -> list[Path]:
    """Copy a traffic run's files into ``out`` (each written atomically); an existing file is
    replaced only with ``force`` (FileExistsError naming it otherwise)."""
    from registration.io.atomic import write_bytes_atomic

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for p in paths:
        target = out / p.name
        if target.exists() and not force:
            raise FileExistsError(f"{target} exists: export with overwrite or into a new folder")
        write_bytes_atomic(target, p.read_bytes())
        written.append(target)
    return written


def zip_files(folder: Path, paths: list[Path]) -> bytes:
    """``paths`` (under ``folder``) as a zip in memory, with their paths relative to ``folder``;
    images, video and GeoPackages stored as they are (already compressed), text deflated."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for p in paths:
            method = zipfile.ZIP_STORED if p.suffix.lower() in STORED else zipfile.ZIP_DEFLATED
            z.write(p, p.relative_to(folder).as_posix(), compress_type=method)
    return buf.getvalue()


def _crs_name(georef) -> str:
    crs = georef.crs
    if crs is None:
        return "no CRS known (a world file without .prj)"
    epsg = georef.epsg
    return f"EPSG:{epsg}" if epsg is not None else crs.name
