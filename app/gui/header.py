"""The app's own panels, above the views' folders: the header (status line, step checklist, view
buttons, the running job with its progress and Cancel) and the Inputs folder (paths, uploads).

Like the views' panels they own their viser handles and offer typed callbacks; the app
(:mod:`app.gui.server`) decides what they show.
"""

from __future__ import annotations

from collections.abc import Callable

from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.state import MODES, STEPS
from app.gui.views.widgets import ClientCallback, on_press

STEP_VIEWS = {
    "calibrated": "Calibrate",
    "seeded": "Seed",
    "reference registered": "Seed",
    "sequence registered": "Sequence",
    "evaluated": "Evaluate",
    "traffic found": "Traffic",
}
"""The view where each step of :data:`app.gui.state.STEPS` is done."""
NEXT = {
    "calibrated": "set γ in **Calibrate** (slider, lines along streets, or the automatic estimate)",
    "seeded": "in **Seed**, click a point on the frame, then the same point on the map",
    "reference registered": "in **Seed**, run the fine step (it runs by itself after a seed click)",
    "sequence registered": "in **Sequence**, press *Register all frames*",
    "evaluated": "in **Evaluate**, mark ground points in several frames, then *Compute Table 2*",
    "traffic found": "in **Traffic**, press *Find vehicles* for tracks and speeds on the map",
}
"""What to do for each step, shown once it is the first not done."""


def view_labels(steps: dict[str, bool], mode: str) -> dict[str, str]:
    """Each view's button label: the active one marked ▶, the ones whose steps are done ✓."""
    labels = {}
    for m in MODES:
        done = all(steps[s] for s, v in STEP_VIEWS.items() if v == m)
        labels[m] = ("▶ " if m == mode else "") + m + (" ✓" if done else "")
    return labels


class HeaderPanel:
    """Status line, step checklist, view buttons and the running job."""

    def __init__(self, gui) -> None:
        self.status = gui.add_markdown("**aerialreg** starting ...")
        self.steps_md = gui.add_markdown("")
        self.mode_buttons = gui.add_button_group("View", list(MODES))
        self._mode_of_label = {m: m for m in MODES}  # the buttons' labels as last shown
        self.job_md = gui.add_markdown("", visible=False)
        self.progress = gui.add_progress_bar(0.0, visible=False)
        self.btn_cancel = gui.add_button("Cancel", color="red", visible=False)

    def on_view_chosen(self, callback: Callable[[str, Client], None]) -> None:
        """``callback(mode, client)`` when a view button is pressed."""

        def chosen(event) -> None:
            mode = self._mode_of_label.get(event.target.value)
            if mode is not None:
                callback(mode, event.client)

        self.mode_buttons.on_click(chosen)

    def on_cancel(self, callback: ClientCallback) -> None:
        on_press(self.btn_cancel, callback)

    def show_status(self, text: str) -> None:
        self.status.content = text

    def show_steps(self, steps: dict[str, bool], mode: str, stale: str = "") -> None:
        """The view buttons, the checklist (the active view's steps highlighted), what to do
        next, and ``stale``: what the registration result was made with that the settings no
        longer are."""
        labels = view_labels(steps, mode)
        if list(self.mode_buttons.options) != list(labels.values()):
            self._mode_of_label = {label: m for m, label in labels.items()}
            self.mode_buttons.options = list(labels.values())
        items = []
        for s in STEPS:
            mark = "✓" if steps[s] else "○"
            cls = "done" if steps[s] else ""
            if STEP_VIEWS[s] == mode:
                cls += " active"
            items.append(f'<span class="{cls.strip()}">{mark} {s}</span>')
        todo = [s for s in STEPS if not steps[s]]
        nxt = f"**Next:** {NEXT[todo[0]]}." if todo else "All steps done."
        if stale:
            nxt += (
                f"\n\n⚠ **The registration result is stale**: it was made with {escape_md(stale)}. "
                "Register the sequence again to use the current settings."
            )
        self.steps_md.content = f'<div class="aerialreg-steps">{" → ".join(items)}</div>\n\n{nxt}'

    def show_job(self, text: str | None) -> None:
        """The running job's line (markdown) and its Cancel button; None hides both."""
        if text is None:
            self.job_md.visible = False
            self.btn_cancel.visible = False
            return
        self.job_md.content = text
        self.job_md.visible = True
        self.btn_cancel.visible = True

    def show_job_progress(self, text: str) -> None:
        """The running job's line only (the Cancel button as it is)."""
        self.job_md.content = text
        self.job_md.visible = True

    def show_progress(self, percent: float | None) -> None:
        """The progress bar at ``percent`` (0..100); None hides it."""
        if percent is None:
            self.progress.visible = False
            return
        self.progress.visible = True
        self.progress.value = percent


class InputsPanel:
    """The Inputs folder: the two paths, Open, the two uploads and where files may come from."""

    def __init__(self, gui) -> None:
        with gui.add_folder("Inputs", expand_by_default=False):
            self.frames_text = gui.add_text("Frames (video, folder, glob)", "")
            self.base_text = gui.add_text("Base map image", "")
            self.open_btn = gui.add_button("Open paths")
            self.upload_frames = gui.add_upload_button("Upload frames (video)", icon=None)
            self.upload_base = gui.add_upload_button("Upload base map", icon=None)
            self.inputs_md = gui.add_markdown("")

    def on_open(self, callback: ClientCallback) -> None:
        on_press(self.open_btn, callback)

    def on_upload(self, callback: Callable[[str, object, Client], None]) -> None:
        """``callback(kind, uploaded file, client)``, kind ``"frames"`` or ``"base"``; the file
        has ``name`` and ``content`` (bytes)."""
        for kind, button in (("frames", self.upload_frames), ("base", self.upload_base)):
            button.on_upload(
                lambda event, kind=kind: callback(kind, event.target.value, event.client)
            )

    @property
    def paths(self) -> tuple[str, str]:
        """The frames' and the base map's path as typed (unchecked)."""
        return str(self.frames_text.value), str(self.base_text.value)

    def show_path(self, kind: str, path: str) -> None:
        """Put ``path`` into the box of ``kind`` (``"frames"`` or ``"base"``)."""
        (self.frames_text if kind == "frames" else self.base_text).value = path

    def show_info(self, text: str) -> None:
        self.inputs_md.content = text
