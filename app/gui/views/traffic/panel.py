"""Traffic view: its panel (frame rate and ground sampling distance, *Find vehicles*, the run's
summary, the frame shown, the selected track's speed chart, the road sections and their counts,
the downloads)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import viser.uplot as up

from app.gui.context import Client
from app.gui.views.widgets import ClientCallback, on_change, on_choice, on_press

DOWNLOADS = ("tracks.csv", "trajectories.geojson", "velocity_field.tif", "counts.csv")
"""The files of a traffic run the panel sends (researchers' formats, docs/traffic.md)."""


SECTIONS_NOTE = (
    "A line across a road: *Draw a section*, then click its two ends on the map. Each "
    "section counts the tracked vehicles that cross it, in each direction (counts.csv)."
)


class TrafficPanel:
    """Widgets of the Traffic view: typed values and callbacks."""

    def __init__(self, gui) -> None:
        self.fps = gui.add_number(
            "Frame rate (frames/s)",
            0.0,
            min=0.0,
            max=1000.0,
            step=0.01,
            hint="0: the video's own timestamps (image frames need it given)",
        )
        self.gsd = gui.add_number(
            "Ground sampling distance (m per map px)",
            0.0,
            min=0.0,
            max=1000.0,
            step=0.001,
            hint="0: from the base map's projected CRS",
        )
        self.btn_find = gui.add_button("Find vehicles")
        self.summary_md = gui.add_markdown("")
        self.frame_slider = gui.add_slider("Frame", 0, 1, 1, 0)
        self.play = gui.add_checkbox("Play", False, hint="each vehicle's box, frame by frame")
        self.show_frame = gui.add_checkbox(
            "Registered frame under the boxes", True, hint="off: the boxes over the map alone"
        )
        self.track = gui.add_number("Track id", -1, min=-1, step=1)
        self.track_md = gui.add_markdown("")
        self.plot = gui.add_uplot(
            data=(np.array([0.0, 1.0]), np.array([np.nan, np.nan])),
            series=(
                up.Series(label="frame"),
                up.Series(label="speed (m/s)", stroke="#e8590c", width=2),
            ),
            title="Speed of the selected track",
            scales={"x": up.Scale(time=False, auto=True), "y": up.Scale(auto=True)},
            axes=(up.Axis(label="frame"), up.Axis(label="m/s")),
            aspect=1.8,
            visible=False,
        )
        with gui.add_folder("Road sections", expand_by_default=False):
            self.sections_md = gui.add_markdown(SECTIONS_NOTE)
            self.sections = gui.add_button_group("Sections", ("Draw a section", "Remove the last"))
            self.counts_md = gui.add_markdown("")
        self.download = gui.add_button_group("Download", DOWNLOADS)

    # ---------------------------------------------------------------- callbacks
    def on_find(self, callback: ClientCallback) -> None:
        on_press(self.btn_find, callback)

    def on_settings_changed(self, callback: Callable[[float, float], None]) -> None:
        """``callback(fps, gsd)`` when either number changes."""
        on_change(self.fps, float, lambda v, client: callback(v, float(self.gsd.value)))
        on_change(self.gsd, float, lambda v, client: callback(float(self.fps.value), v))

    def on_frame_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.frame_slider, int, callback)

    def on_show_frame_changed(self, callback: Callable[[bool, Client], None]) -> None:
        on_change(self.show_frame, bool, callback)

    @property
    def frame_shown(self) -> bool:
        """Whether the registered frame is drawn under the boxes."""
        return bool(self.show_frame.value)

    def on_track_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.track, int, callback)

    def on_sections(self, *, draw: ClientCallback, remove_last: ClientCallback) -> None:
        on_choice(self.sections, {"Draw a section": draw, "Remove the last": remove_last})

    def on_download(self, callback: Callable[[str, Client], None]) -> None:
        on_choice(
            self.download,
            {name: (lambda client, n=name: callback(n, client)) for name in DOWNLOADS},
        )

    # ---------------------------------------------------------------- values
    def configure(self, n_frames: int) -> None:
        self.frame_slider.max = max(n_frames - 1, 1)
        self.frame_slider.disabled = n_frames <= 1

    def show_settings(self, fps: float, gsd: float) -> None:
        self.fps.value = float(fps)
        self.gsd.value = float(gsd)

    @property
    def playing(self) -> bool:
        return bool(self.play.value)

    @property
    def frame(self) -> int:
        return int(self.frame_slider.value)

    @frame.setter
    def frame(self, k: int) -> None:
        self.frame_slider.value = int(k)

    def show_summary(self, text: str) -> None:
        self.summary_md.content = text

    def show_counts(self, text: str) -> None:
        self.counts_md.content = text

    def show_track(self, track_id: int, frames, speed, text: str) -> None:
        """The selected track's speed over its frames (none: ``track_id`` -1)."""
        if self.track.value != track_id:
            self.track.value = int(track_id)
        self.track_md.content = text
        if track_id < 0 or not len(frames):
            self.plot.visible = False
            return
        self.plot.data = (np.asarray(frames, float), np.asarray(speed, float))
        self.plot.visible = True
