"""Earlier results of a project: a run that could not continue the project's result (γ, the
seed, the reference frame or the settings changed) moves it aside as ``result.prev-N`` and starts
a new one. The Sequence view lists them with what they were made with and restores one: it
becomes the project's result again (the current one moved aside in its place) and the app's
settings return to the ones it was made with, so that it is not stale.
"""

from __future__ import annotations

import json
from pathlib import Path

from app.gui.context import Client, ViewContext
from app.gui.messages import browser_message
from app.gui.state import TRANSFORMS
from registration.run.config import PRESETS


class EarlierResults:
    """The Sequence view's *Earlier results* folder: list and restore."""

    def __init__(self, ctx: ViewContext, panel, on_restored) -> None:
        self.ctx = ctx
        self.state = ctx.state
        self.panel = panel
        self.on_restored = on_restored  # called with the restored folder, after the swap
        self._by_label: dict[str, Path] = {}
        panel.on_restore(self.restore)

    def refresh(self) -> None:
        """List the project's earlier results, newest first."""
        labels = {}
        for path in reversed(self.ctx.project.earlier_results()):
            labels[describe(path)] = path
        self._by_label = labels
        self.panel.show_earlier(tuple(labels))

    def restore(self, label: str, client: Client = None) -> bool:
        """Restore the earlier result shown as ``label``, as the app's one job (so never while
        a registration writes the result)."""
        path = self._by_label.get(label)
        if path is None:
            self.ctx.notify(
                client, "Nothing to restore", "Choose an earlier result first", color="yellow"
            )
            return False

        def job(progress) -> None:
            try:
                meta = json.loads((path / "result.json").read_text())
                kept = self.ctx.project.restore_result(path)
            except (OSError, ValueError) as exc:
                self.ctx.notify(client, "Could not restore", browser_message(exc), color="red")
                return
            with self.state.lock:
                apply_settings(self.state, meta)
                self.state.result_dir = str(self.ctx.project.result_dir)
                self.state.revision += 1
            self.on_restored(self.ctx.project.result_dir)
            self.refresh()
            self.ctx.save()
            self.ctx.state_changed()
            moved = f"; the result it replaces is kept as {kept.name}" if kept else ""
            self.ctx.notify(
                client,
                "Result restored",
                f"{path.name} is the project's result again, with the settings it was made "
                f"with{moved}",
                color="green",
            )

        return self.ctx.run_job("restore an earlier result", job, client)


def describe(path: Path) -> str:
    """``result.prev-N``: frames ok, γ, seed and reference frame it was made with."""
    try:
        meta = json.loads((path / "result.json").read_text())
    except (OSError, ValueError):
        return f"{path.name}: unreadable"
    records = list((path / "frames").glob("*.json")) if (path / "frames").is_dir() else []
    n_ok = 0
    for rec in records:
        try:
            n_ok += json.loads(rec.read_text()).get("status") == "ok"
        except (OSError, ValueError):
            pass
    return (
        f"{path.name}: {n_ok}/{meta.get('n_frames', '?')} frames ok, γ {float(meta.get('gamma', 0)):.4f}, "
        f"reference frame {meta.get('reference_frame', 0)}, {meta.get('preset') or 'custom'} preset"
    )


def apply_settings(state, meta: dict) -> None:
    """The app's settings a result was made with (call under the lock)."""
    state.gamma = float(meta["gamma"])
    state.gamma_set = True
    state.reference_frame = int(meta.get("reference_frame", 0))
    seed = meta.get("seed")
    pairs = [] if seed is None else ([seed] if not isinstance(seed[0], list) else seed)
    state.seed_frame = state.seed_base = state.seed2_frame = state.seed2_base = None
    if pairs:
        state.seed_frame, state.seed_base = tuple(pairs[0][:2]), tuple(pairs[0][2:])
    if len(pairs) > 1:
        state.seed2_frame, state.seed2_base = tuple(pairs[1][:2]), tuple(pairs[1][2:])
    preset = meta.get("preset")
    if preset in PRESETS:
        state.preset = preset
    config = meta.get("config") or {}
    degree = (config.get("fine") or {}).get("degree")
    names = [name for name, d in TRANSFORMS.items() if d == degree]
    if names:
        state.transform = names[0]
    if "run_local" in config:
        state.run_local = bool(config["run_local"])
    if "adjust" in config:
        state.adjust = config["adjust"] is not None
