"""The app's one mutable state object, guarded by one lock, and its session (project.json) form.

Shared results live here (the reference frame's coarse and fine fits, the registration result,
Table 2), so views read the state, never each other.
"""

from __future__ import annotations

import copy
import math
import threading
from dataclasses import dataclass, field
from typing import Any

from app.gui.controlpoints import Edits
from registration.lens import Camera

MODES = ("Calibrate", "Seed", "Sequence", "Evaluate", "Traffic")
OVERLAYS = ("blend", "checkerboard", "flicker")
TRANSFORMS = {"projective": 1, "polyprojective 2": 2, "polyprojective 3": 3}
"""Global transform choices: name -> polyprojective degree (degree 1 = projective)."""
ANCHORS = ("reference", "mean")
STEPS = (
    "calibrated",
    "seeded",
    "reference registered",
    "sequence registered",
    "evaluated",
    "traffic found",
)
UNDO_DEPTH = 50


@dataclass(frozen=True)
class PendingMark:
    """A mark proposed to the analyst and not yet confirmed (it counts nowhere until then).

    Attributes:
        score: the correlation of the match (NaN when none).
        offset_px: distance from the registration's prediction, raw px (NaN when not refined).
        confirmable: False when the mark is only the registration's prediction, which measures
            nothing: the analyst must click the point instead.
        note: why it was not refined, or what suggested it.
    """

    score: float = math.nan
    offset_px: float = math.nan
    confirmable: bool = True
    note: str = ""

    def to_json(self) -> list:
        return [_num(self.score), _num(self.offset_px), bool(self.confirmable), self.note]

    @classmethod
    def from_json(cls, values: list) -> PendingMark:
        """From :meth:`to_json`'s list (or an older project's ``[score]``)."""
        score = math.nan if values[0] is None else float(values[0])
        if len(values) < 4:
            return cls(score)
        offset = math.nan if values[1] is None else float(values[1])
        return cls(score, offset, bool(values[2]), str(values[3]))


def _num(value: float) -> float | None:
    """JSON has no NaN: None for it."""
    return float(value) if math.isfinite(value) else None


@dataclass
class ReferenceFit:
    """The reference frame's inter-sensor fits (paper 4.3) and what they were computed for.

    Attributes:
        key: γ, seeds, reference frame, preset and transform the fits belong to.
        coarse: ``global_registration.CoarseResult``.
        fine_auto: the fine step's ``FineResult`` as REQCON left it (None before the fine step).
        fine: the fine result the run uses: ``fine_auto``, or a re-fit with the analyst's
            control-point edits.
    """

    key: dict
    coarse: Any
    fine_auto: Any = None
    fine: Any = None


@dataclass
class AppState:
    """Everything the analyst decided plus the computed results the views share.

    Pixel coordinates follow the project's conventions: frame points are RAW frame pixels (as
    recorded) unless named otherwise; base points are base-map pixels.

    Attributes:
        lock: the one lock for all fields (re-entrant so helpers can nest).
        frames_path, base_path: the current inputs (None until chosen / built).
        n_frames, frame_size, base_size: of the opened inputs; sizes are (W, H) pixels.
        mode: which view is shown (one of :data:`MODES`).
        gamma: Harris γ chosen for the camera (dimensionless); ``gamma_set`` once the analyst
            chose or estimated it.
        calib_frame: frame index shown in the Calibrate view.
        lines: the analyst's polylines, each a list of raw (x, y) pixels.
        line_open: True while the last polyline still takes clicks.
        seed_frame, seed_base: the seed correspondence: raw reference-frame pixel, base pixel;
            ``seed2_frame``, ``seed2_base``: an optional second pair (heading and scale).
        seed2_typed: ``(heading_deg, scale)`` the analyst typed, or None; pair 2 is then computed
            from it (:func:`app.gui.calls.second_seed_from_similarity`) and follows pair 1.
        seed_pair: which pair the next clicks place (1 or 2).
        reference_frame: index of the reference frame (paper: the first).
        preset: registration.run.config preset name; ``transform`` a :data:`TRANSFORMS` name;
            ``run_local``: compute the local displacement field; ``adjust``: adjust the
            sequence once every frame is registered (``registration.adjustment``).
        cp_edits: the analyst's control-point edits of the reference frame (for ``reference``'s
            key only).
        reference: :class:`ReferenceFit` or None (saved in the project's reference.npz).
        result_dir: the registration result folder (str) or None; ``result`` the opened
            ``registration.run.result.RegistrationResult`` (not saved).
        seq_frame, overlay, opacity, vector_scale, stage: Sequence view settings
            (``vector_scale`` 0 = automatic).
        points: marked ground points ``{name: {frame index: (x, y) raw px}}``.
        pending: marks proposed and not yet confirmed ``{(name, frame): PendingMark}``.
        point_name, eval_frame: the point being marked and the frame shown in Evaluate.
        anchor: what Table 2 measures a point's motion from (:data:`ANCHORS`).
        report: the last ``registration.evaluation.report.EvaluationReport`` of Table 2 (not saved).
        traffic_fps, traffic_gsd: the Traffic view's frame rate (frames/s; 0 = the video's own
            timestamps) and ground sampling distance (m per base px; 0 = from the map's CRS).
        traffic_frame: the frame the Traffic view shows.
        traffic_sections: road sections drawn in the Traffic view, each ``[a, b]`` (base px),
            named S1, S2, ... in order.
        traffic: the last traffic run (``app.gui.views.traffic.view.TrafficRun``; not saved).
        zoom: world units per screen pixel of the last camera a browser reported.
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
    gamma_set: bool = False
    calib_frame: int = 0
    lines: list[list[tuple[float, float]]] = field(default_factory=list)
    line_open: bool = False
    seed_frame: tuple[float, float] | None = None
    seed_base: tuple[float, float] | None = None
    seed2_frame: tuple[float, float] | None = None
    seed2_base: tuple[float, float] | None = None
    seed2_typed: tuple[float, float] | None = None
    seed_pair: int = 1
    reference_frame: int = 0
    preset: str = "default"
    transform: str = "polyprojective 2"
    run_local: bool = True
    adjust: bool = True
    cp_edits: Edits = field(default_factory=Edits)
    reference: ReferenceFit | None = None
    result_dir: str | None = None
    result: Any = None
    seq_frame: int = 0
    overlay: str = OVERLAYS[0]
    opacity: float = 0.5
    vector_scale: float = 0.0
    stage: str = "local"
    points: dict[str, dict[int, tuple[float, float]]] = field(default_factory=dict)
    pending: dict[tuple[str, int], PendingMark] = field(default_factory=dict)
    point_name: str = "NW"
    eval_frame: int = 0
    anchor: str = ANCHORS[0]
    report: Any = None
    traffic_fps: float = 0.0
    traffic_gsd: float = 0.0
    traffic_frame: int = 0
    traffic_sections: list[list[tuple[float, float]]] = field(default_factory=list)
    traffic: Any = None
    zoom: float | None = None
    revision: int = 0
    undo_stack: list[dict] = field(default_factory=list, repr=False)

    # Fields written to project.json, and how to read them back.
    _SESSION = (
        "frames_path",
        "base_path",
        "mode",
        "gamma",
        "gamma_set",
        "calib_frame",
        "lines",
        "seed_frame",
        "seed_base",
        "seed2_frame",
        "seed2_base",
        "seed2_typed",
        "reference_frame",
        "preset",
        "transform",
        "run_local",
        "adjust",
        "cp_edits",
        "result_dir",
        "seq_frame",
        "overlay",
        "opacity",
        "vector_scale",
        "stage",
        "points",
        "pending",
        "point_name",
        "eval_frame",
        "anchor",
        "traffic_fps",
        "traffic_gsd",
        "traffic_frame",
        "traffic_sections",
    )
    _UNDOABLE = (
        "seed_frame",
        "seed_base",
        "seed2_frame",
        "seed2_base",
        "seed2_typed",
        "cp_edits",
    )

    # ------------------------------------------------------------------ derived
    @property
    def seed(self) -> tuple[float, float, float, float] | None:
        """``(fx, fy, bx, by)`` once both clicks of pair 1 are made (the CLI's --seed)."""
        if self.seed_frame is None or self.seed_base is None:
            return None
        return (*self.seed_frame, *self.seed_base)

    @property
    def seed2(self) -> tuple[float, float, float, float] | None:
        """The second seed pair, when both of its clicks are made."""
        if self.seed2_frame is None or self.seed2_base is None:
            return None
        return (*self.seed2_frame, *self.seed2_base)

    @property
    def degree(self) -> int:
        return TRANSFORMS.get(self.transform, 2)

    def camera(self, gamma: float | None = None) -> Camera:
        """The frames' camera (:class:`registration.lens.Camera`) at γ ``gamma`` (default: the
        current γ), for the opened frames' size (call under the lock, after inputs are open).

        Raises:
            ValueError: no inputs are open, or γ is not finite.
        """
        if self.frame_size is None:
            raise ValueError("no frames are open")
        return Camera(self.gamma if gamma is None else gamma, *self.frame_size)

    def reference_key(self) -> dict:
        """What the reference frame's fits depend on besides the inputs (call under the lock)."""
        return {
            "gamma": float(self.gamma),
            "seed": None if self.seed is None else [float(v) for v in self.seed],
            "seed2": None if self.seed2 is None else [float(v) for v in self.seed2],
            "reference_frame": int(self.reference_frame),
            "preset": self.preset,
            "degree": self.degree,
        }

    def confirmed_marks(self) -> dict[str, dict[int, tuple[float, float]]]:
        """The evaluation marks without pending proposals: what counts (call under the lock)."""
        pending = set(self.pending)
        return {
            p: {k: xy for k, xy in m.items() if (p, k) not in pending}
            for p, m in self.points.items()
        }

    def current_reference(self) -> ReferenceFit | None:
        """``reference`` when it was computed for the current settings, else None."""
        ref = self.reference
        return ref if ref is not None and ref.key == self.reference_key() else None

    def result_staleness(self) -> str:
        """What the registration result was made with that the current settings no longer are
        ("" when it matches them, or when there is no result; call under the lock)."""
        r = self.result
        if r is None:
            return ""
        why = []
        if abs(float(r.gamma) - float(self.gamma)) > 1e-9:
            why.append(f"γ {float(r.gamma):.4f}, now {float(self.gamma):.4f}")
        if int(r.reference_frame) != int(self.reference_frame):
            why.append(f"reference frame {r.reference_frame}, now {self.reference_frame}")
        return "; ".join(why)

    def steps(self) -> dict[str, bool]:
        """Which of :data:`STEPS` are done (a result made with other settings counts for none)."""
        ref = self.current_reference()
        r = None if self.result_staleness() else self.result
        statuses = [rec.status for rec in r.records] if r is not None else []
        return {
            "calibrated": bool(self.gamma_set),
            "seeded": self.seed is not None,
            "reference registered": bool(
                (ref is not None and ref.fine is not None and ref.fine)
                or (r is not None and r.is_ok(r.reference_frame))
            ),
            "sequence registered": bool(statuses)
            and "pending" not in statuses
            and any(st == "ok" for st in statuses),
            "evaluated": self.report is not None,
            "traffic found": self.traffic is not None and r is not None,
        }

    # ------------------------------------------------------------------ undo
    def push_undo(self) -> None:
        """Remember the seed and control-point edits before a change (call under the lock)."""
        snap = {name: copy.deepcopy(getattr(self, name)) for name in self._UNDOABLE}
        if self.undo_stack and self.undo_stack[-1] == snap:
            return
        self.undo_stack.append(snap)
        del self.undo_stack[:-UNDO_DEPTH]

    def pop_undo(self) -> bool:
        """Restore the last remembered seed and edits; False when there is nothing to undo."""
        if not self.undo_stack:
            return False
        for name, value in self.undo_stack.pop().items():
            setattr(self, name, value)
        self.revision += 1
        return True

    # ------------------------------------------------------------------ session
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
            elif name == "pending":
                value = [[p, int(k), *m.to_json()] for (p, k), m in sorted(value.items())]
            elif name in ("lines", "traffic_sections"):
                value = [[[float(x), float(y)] for x, y in line] for line in value]
            elif name == "cp_edits":
                value = value.to_json()
            elif isinstance(value, tuple):
                value = [float(v) for v in value]
            out[name] = value
        return out

    def replace_session(self, data: dict[str, Any]) -> None:
        """Reset every saved field to its default, then restore ``data`` (another project)."""
        fresh = AppState()
        for name in self._SESSION:
            setattr(self, name, copy.deepcopy(getattr(fresh, name)))
        self.undo_stack.clear()
        self.apply_session(data)

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
                elif name == "pending":
                    value = {(str(e[0]), int(e[1])): PendingMark.from_json(e[2:]) for e in value}
                elif name in ("lines", "traffic_sections"):
                    value = [[(float(x), float(y)) for x, y in line] for line in value]
                elif name in (
                    "seed_frame",
                    "seed_base",
                    "seed2_frame",
                    "seed2_base",
                    "seed2_typed",
                ):
                    value = None if value is None else (float(value[0]), float(value[1]))
                elif name in ("gamma", "opacity", "vector_scale", "traffic_fps", "traffic_gsd"):
                    value = float(value)
                elif name in (
                    "calib_frame",
                    "reference_frame",
                    "seq_frame",
                    "eval_frame",
                    "traffic_frame",
                ):
                    value = int(value)
                elif name in ("gamma_set", "run_local", "adjust"):
                    value = bool(value)
                elif name == "cp_edits":
                    value = Edits.from_json(value)
                elif name == "mode" and value not in MODES:
                    continue
                elif name == "overlay" and value not in OVERLAYS:
                    continue
                elif name == "transform" and value not in TRANSFORMS:
                    continue
                elif name == "anchor" and value not in ANCHORS:
                    continue
            except (TypeError, ValueError, KeyError, IndexError):
                continue
            setattr(self, name, value)
