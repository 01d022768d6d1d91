"""Traffic view: the vehicles on the registered video, on the map (``registration.traffic``).

*Find vehicles* runs the traffic stage on the project's registration result as the app's job
(progress and Cancel in the header; resumable: a cancelled run continues where it stopped),
into the project's ``traffic/`` folder, the same files ``aerialreg traffic`` writes. The map then
shows every track, each step coloured by its speed (blue slow, red fast), and the vehicles of
the frame chosen with the slider; a click near a track, or its id, selects it and charts its
speed over its frames. The run's files download from the panel. The frame rate comes from the
video's timestamps or is given here; metres from the map's projected CRS or a ground sampling
distance given here (the stage refuses in one line when neither is known). Road sections the
analyst draws (two clicks across a road) count the tracked vehicles crossing them in each
direction (``registration.traffic.count_sections``; ``counts.csv`` beside the run's files).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.gui import scene2d
from app.gui.context import Client
from app.gui.messages import browser_message
from app.gui.views.base import PLAY_SIDE_FRACTION, PlayClock, View
from app.gui.views.frames import RegisteredFrames, frame_preview_side
from app.gui.views.traffic.panel import TrafficPanel
from app.gui.views.traffic.scene import TrafficScene, speed_colours

TRAFFIC_DIR = "traffic"
PICK_RADIUS_PX = 20.0
"""A click within this many screen-sized map pixels of a track selects it."""


@dataclass
class TrafficRun:
    """A finished traffic run: its ``summary`` (``summary.json``), its tracks
    (``registration.traffic.TrackRows``) and their positions in base px (``base_xy``, one
    ``(M, 2)`` array per track), the speed shown as red (``top_speed``, m/s), its metric frame
    (``registration.traffic.MetricFrame``)."""

    out: Path
    summary: dict
    tracks: list
    base_xy: list[np.ndarray]
    top_speed: float
    metric: object


class TrafficView(View):
    MODE = "Traffic"
    CLICKABLE = ("base",)

    panel: TrafficPanel
    scene: TrafficScene

    def make_scene(self, scene, root_name):
        return TrafficScene(scene, root_name)

    def make_panel(self, gui):
        return TrafficPanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.on_find(self.find)
        p.on_settings_changed(self.set_settings)
        p.on_frame_changed(lambda k, client: self.set_frame(k))
        p.on_show_frame_changed(
            lambda on, client: self.submit("traffic-vehicles", self.draw_vehicles)
        )
        p.on_track_changed(lambda tid, client: self.select_track(tid))
        p.on_download(self.download)
        p.on_sections(draw=self.start_section, remove_last=self.remove_last_section)
        self.frames = RegisteredFrames(self.ctx, self._result)
        self.selected = -1
        self._drawing = False
        self._section_start: tuple[float, float] | None = None
        self._stop = threading.Event()
        threading.Thread(target=self._ticker, name="traffic-ticker", daemon=True).start()

    def shutdown(self) -> None:
        self._stop.set()

    def _result(self):
        with self.state.lock:
            return self.state.result

    def _ticker(self) -> None:
        """Playback clock: the next frame every ``PLAY_S`` (base.py) while *Play* is on; when
        it stops, the frame shown is drawn again from the full-size preview (posts; never
        draws itself)."""
        clock = PlayClock()
        was_playing = False
        while not self._stop.wait(0.01):
            if not self.visible or self.ctx.inputs is None:
                continue
            playing = self.panel.playing
            if was_playing and not playing:
                self.submit("traffic-vehicles", self.draw_vehicles)
            was_playing = playing
            if clock.due(playing, time.monotonic()):
                with self.state.lock:
                    k = (self.state.traffic_frame + 1) % max(self.ctx.inputs.n_frames, 1)
                self.panel.frame = k  # its callback sets the frame and draws

    # ---------------------------------------------------------------- state
    def on_inputs(self) -> None:
        inp = self.ctx.inputs
        self.scene.make_plane("base", *inp.base_size)
        with self.state.lock:
            fps, gsd, k = self.state.traffic_fps, self.state.traffic_gsd, self.state.traffic_frame
            self.state.traffic = None
        self.panel.configure(inp.n_frames)
        self.panel.show_settings(fps, gsd)
        self.panel.frame = min(k, inp.n_frames - 1)
        self.selected = -1
        self.submit("traffic-load", self.load_existing)

    def on_show(self) -> None:
        self.submit("traffic-render", self.render)

    def set_settings(self, fps: float, gsd: float) -> None:
        with self.state.lock:
            self.state.traffic_fps, self.state.traffic_gsd = float(fps), float(gsd)
        self.ctx.save()

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.ctx.inputs is None:
                return
            self.state.traffic_frame = int(np.clip(k, 0, self.ctx.inputs.n_frames - 1))
        self.ctx.save(soon=True)
        self.submit("traffic-vehicles", self.draw_vehicles)

    @property
    def out_dir(self) -> Path:
        return self.ctx.project.folder / TRAFFIC_DIR

    # ---------------------------------------------------------------- actions
    def find(self, client: Client = None) -> bool:
        """Run the traffic stage on the registration result (a job; resumable)."""
        from registration.traffic import run_traffic

        inp = self.ctx.inputs
        with self.state.lock:
            result, fps, gsd = self.state.result, self.state.traffic_fps, self.state.traffic_gsd
            stale = self.state.result_staleness()
        if inp is None:
            return False
        if result is None or stale:
            why = f" (the result is stale: {stale})" if stale else ""
            self.notify(
                client, "No result", f"Register the sequence first (Sequence view){why}", "yellow"
            )
            return False
        georef = result.georef
        if not gsd and (georef is None or georef.crs is None or not georef.crs.is_projected):
            self.notify(
                client,
                "Metres unknown",
                "The base map has no projected CRS: give the ground sampling distance (metres "
                "per map pixel)",
                "yellow",
            )
            return False
        if not fps and getattr(inp.frames, "video_path", None) is None:
            self.notify(
                client,
                "Frame times unknown",
                "Image frames carry no timestamps: give the frame rate (frames/s)",
                "yellow",
            )
            return False

        def run(progress):
            return run_traffic(
                result,
                inp.frames,
                self.out_dir,
                fps=fps or None,
                gsd_m=gsd or None,
                progress=lambda done, total: progress(done, total, "frames searched"),
                cancel=progress.cancel.is_set,
            )

        def job(progress) -> None:
            progress(0, result.n_frames, "frames searched for vehicles")
            try:
                try:
                    summary = run(progress)
                except FileExistsError:
                    # The folder holds a run of another result or other settings: kept beside.
                    kept = self._archive()
                    self.notify(
                        client, "Starting a new traffic run", f"the last one is kept as {kept}"
                    )
                    summary = run(progress)
            except (ValueError, OSError) as exc:
                self.notify(client, "Traffic not found", browser_message(exc), "red")
                return
            if summary.get("cancelled"):
                self.notify(
                    client,
                    "Traffic cancelled",
                    f"{summary['frames_done']} frames searched are kept; press *Find vehicles* "
                    "to continue",
                    "yellow",
                )
                return
            self.load(summary, result, gsd)
            # A notification shows text as it is: the summary without its markdown.
            self.notify(client, "Traffic found", self.summary_text().replace("**", ""), "green")

        return self.ctx.run_job("find vehicles", job, client)

    def _archive(self) -> str:
        """Move the traffic folder aside (``traffic.prev-N``); returns its new name."""
        import os

        n = 1
        while (self.out_dir.parent / f"{TRAFFIC_DIR}.prev-{n}").exists():
            n += 1
        target = self.out_dir.parent / f"{TRAFFIC_DIR}.prev-{n}"
        os.replace(self.out_dir, target)
        return target.name

    def load_existing(self) -> None:
        """Show the project's last traffic run when it was made from the current result."""
        import json

        path = self.out_dir / "summary.json"
        with self.state.lock:
            result, gsd = self.state.result, self.state.traffic_gsd
        if result is None or not path.is_file():
            return
        try:
            summary = json.loads(path.read_text())
            identity = json.loads((self.out_dir / "traffic.json").read_text())
        except (OSError, ValueError):
            return
        if identity.get("result") != str(Path(result.out_dir).resolve()):
            return
        self.load(summary, result, gsd)

    def load(self, summary: dict, result, gsd: float) -> None:
        """Read the run's tracks, put them on the map and say what was found."""
        from registration.traffic import MetricFrame, read_tracks_csv

        try:
            tracks = read_tracks_csv(self.out_dir / "tracks.csv")
            metric = MetricFrame.for_result(result.georef, gsd or None)
        except (OSError, ValueError) as exc:
            self.ctx.record_error(f"traffic run unreadable: {exc}")
            return
        base_xy = [metric.base_from_metres(t.xy_m) for t in tracks]
        speeds = np.concatenate([t.speed for t in tracks]) if tracks else np.zeros(0)
        top = float(np.percentile(speeds, 95)) if len(speeds) else 1.0
        run = TrafficRun(self.out_dir, summary, tracks, base_xy, max(top, 1.0), metric)
        with self.state.lock:
            self.state.traffic = run
            self.state.revision += 1
        self.panel.show_summary(self.summary_text())
        self.count()
        self.ctx.state_changed()
        self.render()

    def summary_text(self) -> str:
        with self.state.lock:
            run = self.state.traffic
        if run is None:
            return "No vehicles found yet: press *Find vehicles*."
        s = run.summary
        median = s.get("median_speed_mps")
        return (
            f"**{s.get('n_tracks', len(run.tracks))} tracks** from "
            f"{s.get('n_detections', 0)} detections in {s.get('n_used', '?')} of "
            f"{s.get('n_frames', '?')} frames"
            + (f"; median speed {median:.1f} m/s" if median is not None else "")
            + f". Colours: blue slow to red at {run.top_speed:.1f} m/s and above. Times: "
            f"{_time_source(s.get('time_source', '?'))}; metres: {s.get('metric', '?')}. "
            f"Files in {run.out}."
        )

    def select_track(self, track_id: int) -> None:
        self.selected = int(track_id)
        self.submit("traffic-selected", self.draw_selected)

    # ---------------------------------------------------------------- road sections
    def start_section(self, client: Client = None) -> None:
        """The next two clicks on the map are a new section's ends."""
        self._drawing, self._section_start = True, None
        self.panel.show_counts("**Click the section's first end on the map.**")

    def remove_last_section(self, client: Client = None) -> None:
        with self.state.lock:
            if self.state.traffic_sections:
                self.state.traffic_sections.pop()
        self._drawing, self._section_start = False, None
        self.ctx.save()
        self.submit("traffic-counts", self.count)

    def _section_click(self, xy) -> None:
        if self._section_start is None:
            self._section_start = (float(xy[0]), float(xy[1]))
            self.panel.show_counts("**Now click its other end.**")
        else:
            with self.state.lock:
                self.state.traffic_sections.append(
                    [self._section_start, (float(xy[0]), float(xy[1]))]
                )
            self._drawing, self._section_start = False, None
            self.ctx.save()
        self.submit("traffic-counts", self.count)

    def count(self) -> None:
        """Count the run's tracks across the sections (``counts.csv``) and show them (worker)."""
        from registration.traffic import count_sections, write_counts_csvs

        with self.state.lock:
            run, sections = self.state.traffic, [list(s) for s in self.state.traffic_sections]
        named = [(f"S{i + 1}", a, b) for i, (a, b) in enumerate(sections)]
        self.draw_sections()
        if self._drawing:
            return
        if not named:
            if run is not None:  # no stale counts of removed sections to download
                for name in ("counts.csv", "crossings.csv"):
                    (run.out / name).unlink(missing_ok=True)
            self.panel.show_counts("")
            return
        if run is None:
            self.panel.show_counts(f"{len(named)} section(s): find the vehicles to count them.")
            return
        try:
            counted = count_sections(run.tracks, run.metric, named)
            write_counts_csvs(run.out, counted)
        except (ValueError, OSError) as exc:
            self.ctx.record_error(f"road sections not counted: {exc}")
            self.panel.show_counts(f"Not counted: {browser_message(exc)}")
            return
        rows = ["| section | towards | vehicles | mean speed |", "|---|---|---:|---:|"]
        for sec in counted:
            for d in (1, 2):
                n, speed, heading = sec.direction(d)
                if n:
                    rows.append(f"| {sec.name} | {heading} | {n} | {speed:.1f} m/s |")
            if not sec.crossings:
                rows.append(f"| {sec.name} | – | 0 | – |")
        self.panel.show_counts("\n".join(rows))

    def draw_sections(self) -> None:
        with self.state.lock:
            sections = [list(s) for s in self.state.traffic_sections]
        with self.ctx.atomic():
            self.scene.draw_sections(sections, self._section_start)

    def on_click(self, plane: str, xy, client) -> None:
        """A click draws a road section's end while one is being drawn, else selects the
        nearest track."""
        if self._drawing and plane == "base":
            self._section_click(xy)
            return
        with self.state.lock:
            run, zoom = self.state.traffic, self.state.zoom
        if run is None or plane != "base":
            return
        # The pick radius in map px follows the zoom (screen px -> world -> map px).
        radius = PICK_RADIUS_PX * (zoom / scene2d.WORLD_PER_PX if zoom else 1.0)
        best, best_d = -1, float("inf")
        for tr, b in zip(run.tracks, run.base_xy, strict=True):
            d = float(np.min(np.hypot(*(b - np.asarray(xy, float)).T))) if len(b) else np.inf
            if d < best_d:
                best, best_d = tr.track_id, d
        self.select_track(best if best_d <= radius else -1)

    def download(self, name: str, client: Client = None) -> bool:
        path = self.out_dir / name
        if not path.is_file():
            self.notify(
                client, "Nothing to download", f"{name}: run *Find vehicles* first", "yellow"
            )
            return False
        self.ctx.send_download(client, name, path.read_bytes())
        return True

    # ---------------------------------------------------------------- drawing (worker)
    def render(self) -> None:
        inp = self.ctx.inputs
        if inp is None or "base" not in self.scene.planes:
            return
        with self.ctx.atomic():
            self.scene.show_base(scene2d.to_rgb(inp.base_preview(2 * self.ctx.display_max)))
        self.draw_tracks()
        self.draw_vehicles()
        self.draw_selected()
        self.draw_sections()
        self.ctx.shown[self.MODE] = (self.state.revision,)

    def draw_tracks(self) -> None:
        with self.state.lock:
            run = self.state.traffic
        starts, ends, colours = [], [], []
        if run is not None:
            for tr, b in zip(run.tracks, run.base_xy, strict=True):
                if len(b) < 2:
                    continue
                starts.append(b[:-1])
                ends.append(b[1:])
                colours.append(speed_colours(0.5 * (tr.speed[:-1] + tr.speed[1:]), run.top_speed))
        with self.ctx.atomic():
            if starts:
                self.scene.draw_tracks(
                    np.concatenate(starts), np.concatenate(ends), np.concatenate(colours)
                )
            else:
                self.scene.draw_tracks(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))

    def vehicles_at(self, k: int) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
        """``(track ids, base px (N, 2), speeds (N,), boxes (N, 4, 2) base px)`` of the vehicles
        tracked in frame ``k``; a box is the track's width and length around its centre, along
        its direction of travel (its mean direction where it stands)."""
        with self.state.lock:
            run = self.state.traffic
        ids, xy, speed, boxes = [], [], [], []
        if run is not None:
            for tr, b in zip(run.tracks, run.base_xy, strict=True):
                i = np.flatnonzero(tr.frames == k)
                if len(i):
                    ids.append(tr.track_id)
                    xy.append(b[i[0]])
                    speed.append(tr.speed[i[0]])
                    boxes.append(run.metric.base_from_metres(_box_m(tr, i[0])))
        return (
            ids, np.array(xy).reshape(-1, 2), np.array(speed, float),
            np.array(boxes).reshape(-1, 4, 2),
        )  # fmt: skip

    def draw_vehicles(self) -> None:
        """The vehicles of the frame shown, over that frame registered to the map (the local
        stage's, as the tracks were measured; from the smaller playback preview while
        playing)."""
        with self.state.lock:
            k, run = self.state.traffic_frame, self.state.traffic
        ids, xy, speed, boxes = self.vehicles_at(k)
        top = run.top_speed if run is not None else 1.0
        reg, side = None, 2 * self.ctx.display_max
        if run is not None and self.panel.frame_shown:
            if self.panel.playing:
                side = int(PLAY_SIDE_FRACTION * self.ctx.display_max)
            reg = self.frames.registered(k, "local", side)
        patch = None
        if reg is not None:
            from registration.render import viz

            crop, mask, _ = reg
            # The frame where it has pixels, the map around them (the footprint's box).
            patch = viz.blend(crop, self.frames.map_under(reg, side), 1.0, mask=mask)
        with self.ctx.atomic():
            self.scene.show_registered(patch, None if reg is None else reg[2])
            self.scene.draw_vehicles(xy, speed_colours(speed, top), boxes)
        if reg is not None:  # read the next frames ahead, as playback will want them
            guess = frame_preview_side(reg[0].shape[1], reg[0].shape[0])
            self.ctx.inputs.prefetch([k + 1, k + 2], preview_sides=(guess,))

    def draw_selected(self) -> None:
        with self.state.lock:
            run = self.state.traffic
        tid = self.selected
        chosen = None
        if run is not None and tid >= 0:
            chosen = next(
                ((t, b) for t, b in zip(run.tracks, run.base_xy, strict=True) if t.track_id == tid),
                None,
            )
        if chosen is None:
            with self.ctx.atomic():
                self.scene.draw_selected(np.zeros((0, 2)), np.zeros((0, 2)))
            text = "Click near a track (or type its id) to see its speed." if run else ""
            self.panel.show_track(-1, [], [], text)
            return
        tr, b = chosen
        with self.ctx.atomic():
            self.scene.draw_selected(b[:-1], b[1:])
        speed = tr.speed
        self.panel.show_track(
            tr.track_id,
            tr.frames,
            speed,
            f"Track **{tr.track_id}**: frames {tr.frames[0]}-{tr.frames[-1]}, speed "
            f"{np.mean(speed):.1f} m/s mean, {np.max(speed):.1f} max; "
            f"{tr.length_m:.1f} m long.",
        )


def _time_source(text: str) -> str:
    """The run's time source as the browser says it (the library names the command line's
    ``--fps F`` for a frame rate given)."""
    return f"the frame rate given, {text[6:]} frames/s" if text.startswith("--fps ") else text


def _box_m(track, i: int) -> np.ndarray:
    """``(4, 2)`` metres: track row ``i``'s box (its width and length, along its direction of
    travel there, or its mean direction where it barely moves)."""
    v = track.velocity[i]
    if np.hypot(*v) < 0.5:
        v = track.velocity.mean(axis=0)
    u = v / max(np.hypot(*v), 1e-9) if np.hypot(*v) > 1e-9 else np.array([1.0, 0.0])
    n = np.array([-u[1], u[0]])
    half_l, half_w = 0.5 * track.length_m * u, 0.5 * track.width_m * n
    c = track.xy_m[i]
    return np.array(
        [c + half_l + half_w, c + half_l - half_w, c - half_l - half_w, c - half_l + half_w]
    )
