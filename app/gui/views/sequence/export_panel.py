"""Sequence view: the export's panel (formats, options, the result of the last export, the files
to download, the overwrite dialog); its actions are :mod:`app.gui.views.sequence.export`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.views.widgets import ClientCallback, on_press

FORMAT_LABELS = {
    "geotiff": "GeoTIFF frames",
    "cog": "COG frames",
    "png": "PNG + world files",
    "mosaic": "Mosaic (COG)",
    "mp4": "Video (mp4)",
    "points": "QGIS .points",
    "transforms": "Transforms (JSON)",
    "geojson": "GeoJSON",
    "gpkg": "GeoPackage",
}
"""Format (``registration.gis.export.FORMATS``) -> checkbox label, in the panel's order."""
TRAFFIC = "traffic"
"""The export's one format that is not the registration's: the Traffic view's files."""
TRAFFIC_HINT = (
    "the Traffic view's run of this result: tracks.csv, tracksMeta.csv, recordingMeta.csv, "
    "tracks_wgs84.csv, trajectories.geojson and .gpkg, velocity_field.tif, and counts.csv with "
    "crossings.csv where road sections are drawn"
)
DEFAULT_FORMATS = ("mp4", "transforms")
VECTOR_CRS = {"the map's CRS": None, "WGS 84 (longitude, latitude)": "EPSG:4326"}
NO_DOWNLOAD = "(nothing exported yet)"
ANSWERS = {
    "overwrite": "Overwrite them",
    "new folder": "Write into {folder}",
    "cancel": "Cancel",
}
"""The overwrite dialog's answers and their buttons' labels."""


@dataclass(frozen=True)
class ExportChoices:
    """The export options the analyst chose (``registration.gis.ExportOptions`` without
    ``force``).

    Attributes:
        stage: ``"local"`` or ``"global"``.
        mosaic: ``"median"`` or ``"mean"``.
        fps: frames per second of the video.
        video_scale: the video's size as a share of the map's pixel grid.
        vector_crs: CRS of GeoJSON and GeoPackage coordinates (None: the map's).
        marks: include the evaluation marks.
    """

    stage: str
    mosaic: str
    fps: float
    video_scale: float
    vector_crs: str | None
    marks: bool


class ExportPanel:
    """Widgets of the export (built inside the Sequence view's "Export" folder)."""

    def __init__(self, gui) -> None:
        from registration.gis import FORMATS

        self.intro = gui.add_markdown("")
        self.formats = {
            f: gui.add_checkbox(label, f in DEFAULT_FORMATS, hint=FORMATS[f])
            for f, label in FORMAT_LABELS.items()
        }
        self.formats[TRAFFIC] = gui.add_checkbox("Traffic (tracks, velocity field, counts)", False,
                                                 hint=TRAFFIC_HINT)  # fmt: skip
        gui.add_markdown(
            "_Frames are registered into the map's pixel grid, each cropped to its footprint; "
            "GeoJSON and GeoPackage hold the control points, the frames' footprints and the "
            "evaluation marks._"
        )
        self.georef_md = gui.add_markdown("")
        with gui.add_folder("Export options", expand_by_default=False):
            self.stage = gui.add_dropdown(
                "Export stage", ("local", "global"), initial_value="local"
            )
            self.mosaic = gui.add_dropdown(
                "Mosaic",
                ("median", "mean"),
                initial_value="median",
                hint="median of up to 15 frames spread over the sequence (moving vehicles "
                "vanish), or the mean of all",
            )
            self.video_scale = gui.add_slider("Video scale", 0.25, 1.0, 0.25, 0.5)
            self.fps = gui.add_number("Video frames per second", 5.0, min=0.5, max=60.0, step=0.5)
            self.vector_crs = gui.add_dropdown(
                "GeoJSON / GeoPackage coordinates", tuple(VECTOR_CRS), initial_value="the map's CRS"
            )
            self.marks = gui.add_checkbox("Include the evaluation marks", True)
            gui.add_markdown(
                "_The video is the registered sequence in the map's pixel grid over the "
                "sequence's footprint; with a georeferenced base it gets a world file (.wld, "
                ".prj) that places it in map coordinates._"
            )
        self.btn_export = gui.add_button("Export the ticked formats")
        self.result_md = gui.add_markdown("")
        self.download_pick = gui.add_dropdown("Exported files", (NO_DOWNLOAD,))
        self.btn_download = gui.add_button("Download", disabled=True)

    # ---------------------------------------------------------------- callbacks
    def on_export(self, callback: ClientCallback) -> None:
        on_press(self.btn_export, callback)

    def on_download(self, callback: Callable[[str, Client], None]) -> None:
        """``callback(picked entry, client)`` for the Download button."""
        on_press(self.btn_download, lambda client: callback(str(self.download_pick.value), client))

    # ---------------------------------------------------------------- values
    def chosen(self) -> list[str]:
        """The ticked formats that are available."""
        return [f for f, box in self.formats.items() if box.value and not box.disabled]

    def choices(self) -> ExportChoices:
        return ExportChoices(
            stage=str(self.stage.value),
            mosaic=str(self.mosaic.value),
            fps=float(self.fps.value),
            video_scale=float(self.video_scale.value),
            vector_crs=VECTOR_CRS.get(str(self.vector_crs.value)),
            marks=bool(self.marks.value),
        )

    def show_availability(self, unavailable: set[str], can_export: bool) -> None:
        """Disable the ``unavailable`` formats' boxes, and the Export button unless
        ``can_export``."""
        for f, box in self.formats.items():
            box.disabled = f in unavailable
        self.btn_export.disabled = not can_export

    def show_georef(self, text: str) -> None:
        self.georef_md.content = text

    def show_intro(self, text: str) -> None:
        self.intro.content = text

    @property
    def result_text(self) -> str:
        """What the last export said (markdown)."""
        return str(self.result_md.content)

    @result_text.setter
    def result_text(self, text: str) -> None:
        self.result_md.content = text

    def offer_downloads(self, labels: tuple[str, ...]) -> None:
        """The exported files' entries (none: the Download button is disabled)."""
        self.download_pick.options = labels or (NO_DOWNLOAD,)
        self.download_pick.value = self.download_pick.options[0]
        self.btn_download.disabled = not labels

    def ask_overwrite(
        self,
        gui,
        existing: list[Path],
        folder: Path,
        new_folder: str,
        on_answer: Callable[[str], None],
    ):
        """The overwrite dialog in ``gui`` (one tab's or all); ``on_answer`` gets one of
        :data:`ANSWERS`. Returns the dialog (close it with ``.close()``)."""
        names = ", ".join(escape_md(p.relative_to(folder)) for p in existing[:3])
        more = f" and {len(existing) - 3} more" if len(existing) > 3 else ""
        with gui.add_modal("Files exist") as modal:
            gui.add_markdown(
                f"{len(existing)} of the files to write exist in {escape_md(folder)}: "
                f"{names}{more}."
            )
            for answer, label in ANSWERS.items():
                btn = gui.add_button(
                    label.format(folder=new_folder), color="red" if answer == "overwrite" else None
                )
                btn.on_click(lambda event, a=answer: on_answer(a))
        return modal
