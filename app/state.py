"""The app's one mutable state object, guarded by one lock, and its session (project.json) form."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

MODES = ("Calibrate", "Seed", "Sequence", "Evaluate")
OVERLAYS = ("blend", "checkerboard", "flicker")


@dataclass
class AppState:
    """Everything the analyst decided plus handles to computed results.

    Pixel coordinates follow the project's conventions: frame points are RAW frame pixels (as
    recorded) unless named otherwise; base points are base-map pixels.

    Attributes:
        lock: the one lock for all fields (re-entrant so helpers can nest).
        frames_path, base_path: the current inputs (None until chosen / built).
        n_frames, frame_size, base_size: of the opened inputs; sizes are (W, H) pixels.
        mode: which view is shown (one of :data:`MODES`).
        gamma: Harris γ chosen for the camera (dimensionless).
        calib_frame: frame index shown in the Calibrate view.
        lines: the analyst's polylines, each a list of raw (x, y) pixels.
        line_open: True while the last polyline still takes clicks.
        seed_frame, seed_base: the seed correspondence: raw reference-frame pixel, base pixel.
        reference_frame: index of the reference frame (paper: the first).
        preset: registration.config preset name.
        coarse, fine: the last CoarseResult / FineResult (not saved; recomputed on demand).
        result_dir: the registration result folder (str) or None.
        seq_frame, overlay, opacity, vector_scale, stage: Sequence view settings.
        points: marked ground points ``{name: {frame index: (x, y) raw px}}``.
        point_name, eval_frame: the point being marked and the frame shown in Evaluate.
        revision: bumped on every change (the worker uses it to drop stale renders).
    """

    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)
    frames_path: str | None = None
    base_path: str | None = None
    n_frames: int = 0
    frame_size: tuple[int, int] | None = None
    base_size: tuple[int, int] | None = None
    mode: str = MODES[0]
    gamma: float = 0.0
    calib_frame: int = 0
    lines: list[list[tuple[float, float]]] = field(default_factory=list)
    line_open: bool = False
    seed_frame: tuple[float, float] | None = None
    seed_base: tuple[float, float] | None = None
    reference_frame: int = 0
    preset: str = "default"
    coarse: Any = None
    fine: Any = None
    result_dir: str | None = None
    seq_frame: int = 0
    overlay: str = OVERLAYS[0]
    opacity: float = 0.5
    vector_scale: float = 10.0
    stage: str = "local"
    points: dict[str, dict[int, tuple[float, float]]] = field(default_factory=dict)
    point_name: str = "NW"
    eval_frame: int = 0
    revision: int = 0

    # Fields written to project.json, and how to read them back.
    _SESSION = (
        "frames_path",
        "base_path",
        "mode",
        "gamma",
        "calib_frame",
        "lines",
        "seed_frame",
        "seed_base",
        "reference_frame",
        "preset",
        "result_dir",
        "seq_frame",
        "overlay",
        "opacity",
        "vector_scale",
        "stage",
        "points",
        "point_name",
        "eval_frame",
    )

    @property
    def seed(self) -> tuple[float, float, float, float] | None:
        """``(fx, fy, bx, by)`` once both clicks are made (the CLI's --seed), else None."""
        if self.seed_frame is None or self.seed_base is None:
            return None
        return (*self.seed_frame, *self.seed_base)

    def to_session(self) -> dict[str, Any]:
        """JSON-ready dict of the saved fields (call with the lock held)."""
        out: dict[str, Any] = {}
        for name in self._SESSION:
            value = getattr(self, name)
            if name == "points":
                value = {
                    p: {str(k): [float(v[0]), float(v[1])] for k, v in sorted(frames.items())}
                    for p, frames in value.items()
                }
            elif name == "lines":
                value = [[[float(x), float(y)] for x, y in line] for line in value]
            elif isinstance(value, tuple):
                value = [float(v) for v in value]
            out[name] = value
        return out

    def apply_session(self, data: dict[str, Any]) -> None:
        """Restore saved fields from ``data``; unknown or malformed entries are ignored."""
        for name in self._SESSION:
            if name not in data:
                continue
            value = data[name]
            try:
                if name == "points":
                    value = {
                        str(p): {int(k): (float(v[0]), float(v[1])) for k, v in frames.items()}
                        for p, frames in value.items()
                    }
                elif name == "lines":
                    value = [[(float(x), float(y)) for x, y in line] for line in value]
                elif name in ("seed_frame", "seed_base"):
                    value = None if value is None else (float(value[0]), float(value[1]))
                elif name in ("gamma", "opacity", "vector_scale"):
                    value = float(value)
                elif name in ("calib_frame", "reference_frame", "seq_frame", "eval_frame"):
                    value = int(value)
                elif name == "mode" and value not in MODES:
                    continue
                elif name == "overlay" and value not in OVERLAYS:
                    continue
            except (TypeError, ValueError, KeyError, IndexError):
                continue
            setattr(self, name, value)
