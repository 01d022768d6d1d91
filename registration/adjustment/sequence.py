"""The sequence adjustment over a whole flight, window by window (beyond the paper).

A flight of hours cannot be solved at once, and need not be: a frame's model depends on the
frames it is linked to, which are its neighbours in time. The frames are taken in index order in
overlapping windows of ``window_frames``; each window is solved with the frames before it held
as they were made final (:func:`registration.adjustment.adjust_models` with ``fixed``), and its
first ``final_frames`` frames leave it final (the last window: all of them). A frame is thus
decided with at least ``window_frames - final_frames`` later frames in view, and the cost per
frame does not grow with the flight.

Which windows there are depends only on the number of frames and the configuration
(:func:`window_plan`), and a window's solution only on its frames' per-frame models, control
points, links and the final models before it: a run that resumes from the frames already
final reaches the same models, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from registration.adjustment.fields import FieldSolveConfig
from registration.adjustment.links import link_key, measure_links
from registration.adjustment.map_points import FrameMapPoints
from registration.adjustment.solve import (
    AdjustmentConfig,
    ControlPointSet,
    FrameLinks,
    adjust_models,
)
from registration.geometry import Normalisation, PolyProjective, Projective
from registration.matching import ProbeConfig, textured_probes


@dataclass(frozen=True)
class SequenceAdjustConfig:
    """Settings of the sequence adjustment (none in the paper: it registers each frame alone).

    Attributes:
        window_frames: frames solved together.
        final_frames: frames a window makes final (the window then moves on by this many).
        link_steps: frame ``k`` is linked to ``k + s`` for each ``s`` (same ground seen from
            further apart ties a stretch of frames together, not only neighbours).
        probes: where links are measured (:func:`registration.adjustment.measure_links`).
        link_matcher: how: ``"flow"`` (Lucas-Kanade from the prediction) or ``"ncc"`` (each
            probe's patch searched by correlation).
        solver: the solver's noise model and stopping rule.
        default_control_sigma_px: a frame's control-point noise (base px) where its fine step
            recorded none.
        prior_sigma_px: each frame's own model is a weak prior on its adjusted one, at points
            over its whole outline, with this noise (base px): where control points and links
            are dense the evidence decides; towards the corners, which they rarely reach, a
            polynomial the evidence does not hold would otherwise swing far.
        fields: the local stage made consistent in time by the links
            (:mod:`registration.adjustment.fields`); None keeps every frame's own local stage.
        flag_px: a frame whose predicted error exceeds this (base px) is flagged; so is a
            frame with neighbours but no links to them (where its model puts its neighbours'
            ground, its image does not show it).
    """

    window_frames: int = 40
    final_frames: int = 30
    link_steps: tuple[int, ...] = (1, 5)
    probes: ProbeConfig = field(default_factory=ProbeConfig)
    link_matcher: str = "flow"
    solver: AdjustmentConfig = field(default_factory=AdjustmentConfig)
    default_control_sigma_px: float = 0.3
    prior_sigma_px: float = 1.0
    fields: FieldSolveConfig | None = field(default_factory=FieldSolveConfig)
    flag_px: float = 2.0

    def __post_init__(self) -> None:
        if not 1 <= self.final_frames <= self.window_frames:
            raise ValueError(
                f"final_frames must be 1..window_frames ({self.window_frames}), "
                f"got {self.final_frames}"
            )
        steps = tuple(self.link_steps)
        if not steps or any(int(s) < 1 for s in steps):
            raise ValueError(f"link_steps must be positive frame steps, got {self.link_steps!r}")
        if max(steps) >= self.window_frames:
            raise ValueError(
                f"link_steps must be shorter than window_frames ({self.window_frames}), "
                f"got {max(steps)}"
            )
        object.__setattr__(self, "link_steps", tuple(int(s) for s in steps))
        if self.link_matcher not in ("flow", "ncc"):
            raise ValueError(f"link_matcher must be 'flow' or 'ncc', got {self.link_matcher!r}")
        for name in ("flag_px", "default_control_sigma_px", "prior_sigma_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class Window:
    """Frames ``start .. end - 1`` solved together; ``start .. final_end - 1`` leave final."""

    start: int
    final_end: int
    end: int


# Probes per frame at most (before the texture test): a 852x480 frame at the probes' 24 px
# spacing has 710; a larger frame spaces them wider rather than measuring more.
MAX_PROBES = 720


def probes_for(grey: NDArray, probes: ProbeConfig) -> ProbeConfig:
    """``probes`` with the spacing widened so that a frame of ``grey``'s size has at most
    :data:`MAX_PROBES` (the links' cost and the solve's grow with their number: a 2560x1920
    frame at 24 px would have 8500)."""
    h, w = grey.shape[:2]
    spacing = int(np.ceil(np.sqrt(w * h / MAX_PROBES)))
    return probes if spacing <= probes.grid_px else replace(probes, grid_px=spacing)


def window_plan(n_frames: int, config: SequenceAdjustConfig) -> list[Window]:
    """The windows of a flight of ``n_frames`` (module docstring)."""
    windows, start = [], 0
    while start < n_frames:
        end = min(start + config.window_frames, n_frames)
        final_end = n_frames if end == n_frames else start + config.final_frames
        windows.append(Window(start, final_end, end))
        start = final_end
    return windows


@dataclass(frozen=True)
class FrameAdjustment:
    """One frame's outcome of the sequence adjustment.

    Attributes:
        k: the frame.
        model: its adjusted ``base_from_corrected`` (its own model where it was held fixed).
        window: the window's ``(start, end)`` that made it final.
        n_links: link points that touch it; n_controls: its control points.
        link_rms_px, control_rms_px: RMS residuals (base px) of its links and control points
            (its map points among them) after the adjustment (None where it has none).
        position_sigma_px: standard deviation of its points' positions (base px) from the
            solution's covariance; for the frame held fixed (the reference frame), what its own
            fit to its control points leaves unknown (:func:`_own_fit`).
        predicted_error_px: what the evidence says about its error (base px):
            :func:`predicted_error`.
        flagged: why the frame is likely worse than ``flag_px`` (``""``: it is not).
        moved_px: RMS shift of its control points from its own model to the adjusted one
            (base px).
        n_map_points: the analyst's map points on it; map_point_rms_px: their RMS residual
            (base px) after the adjustment (None without any).
        note: what its map points made of its own evidence (``FrameMapPoints.note``).
    """

    k: int
    model: PolyProjective
    window: tuple[int, int]
    n_links: int
    n_controls: int
    link_rms_px: float | None
    control_rms_px: float | None
    position_sigma_px: float | None
    predicted_error_px: float
    flagged: str
    moved_px: float
    n_map_points: int = 0
    map_point_rms_px: float | None = None
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-able, without the model (the record holds it); the map points' entries only
        where the frame has some."""
        extra = {}
        if self.n_map_points:
            extra = {
                "n_map_points": self.n_map_points,
                "map_point_rms_px": self.map_point_rms_px,
                "note": self.note,
            }
        return {
            "window": list(self.window),
            "n_links": self.n_links,
            "n_controls": self.n_controls,
            "link_rms_px": self.link_rms_px,
            "control_rms_px": self.control_rms_px,
            "position_sigma_px": self.position_sigma_px,
            "predicted_error_px": self.predicted_error_px,
            "flagged": self.flagged,
            "moved_px": self.moved_px,
            **extra,
        }


def predicted_error(
    position_sigma_px: float | None, link_rms_px: float | None, link_sigma_px: float
) -> float:
    """A frame's predicted error (base px): what its evidence leaves unknown (the solution's
    covariance, with each frame's control-point noise as its residuals showed it: a frame whose
    own registration went wrong weighs little, and its position comes from its links), plus
    the part of its links' residuals their expected noise does not explain (the frame's model
    cannot agree with its neighbours')."""
    parts = [position_sigma_px or 0.0]
    if link_rms_px is not None:
        parts.append(np.sqrt(max(link_rms_px**2 - (2.0 * link_sigma_px) ** 2, 0.0)))
    return float(np.sqrt(np.sum(np.square(parts))))


def as_polyprojective(model, width: int, height: int, degree: int = 2) -> PolyProjective:
    """``model`` as a polyprojective (a frame that fell back to a homography or an affine map
    joins the adjustment with the same mapping and room to bend)."""
    if isinstance(model, PolyProjective):
        return model
    proj = Projective.from_matrix(np.asarray(model.matrix, np.float64))
    corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    return PolyProjective.from_projective(
        proj, degree, Normalisation.for_extent(width, height),
        Normalisation.from_points(proj.apply(corners)),
    )  # fmt: skip


@dataclass
class SequenceEvidence:
    """What the adjustment reads of a registered flight.

    Attributes:
        models: each frame's own model (``base_from_corrected``; None for a failed frame).
        controls: each frame's kept control points (None for a failed frame).
        grey: frame ``k``'s raw grey image ``(H, W)`` uint8 (read when its links are measured).
        lens: raw <-> corrected px (``raw_from_corrected``, ``corrected_from_raw``).
        outline: ``(M, 2)`` corrected px spread over the whole frame, corners included (where
            each frame's prior holds, ``SequenceAdjustConfig.prior_sigma_px``).
        fixed: frames whose models are held (the reference frame: the mid base image every
            other frame's control points were measured on is made of it).
        map_points: the analyst's map points of a frame, and what they made of its evidence
            (``models`` and ``controls`` already say it: :func:`apply_map_points`).
        stored_links: ``(k, l) -> (links, key)`` measured earlier (as the frames were
            registered), or None; used where the key says they were measured through the
            models, lens and settings a measurement now would use (:func:`link_key`), so the
            frames need not be read again.
    """

    models: list[PolyProjective | None]
    controls: list[ControlPointSet | None]
    grey: Callable[[int], NDArray]
    lens: object
    outline: NDArray[np.float64]
    fixed: frozenset[int] = frozenset()
    map_points: Mapping[int, FrameMapPoints] = field(default_factory=dict)
    stored_links: Callable[[int, int], tuple[FrameLinks, NDArray] | None] | None = None
    _links: dict = field(default_factory=dict, repr=False)
    _probes: dict = field(default_factory=dict, repr=False)

    def links(
        self,
        k: int,
        l: int,  # noqa: E741 (the second frame)
        probes: ProbeConfig,
        matcher: str = "flow",
    ) -> FrameLinks:
        """Links between frames ``k`` and ``l``, measured once through their own models."""
        if (k, l) not in self._links:
            stored = self.stored_links(k, l) if self.stored_links is not None else None
            if stored is not None and np.array_equal(
                stored[1], link_key(self.models[k], self.models[l], self.lens, probes, matcher)
            ):
                self._links[(k, l)] = stored[0]
                return stored[0]
            if k not in self._probes:
                self._probes[k] = textured_probes(self.grey(k), probes_for(self.grey(k), probes))
            self._links[(k, l)] = measure_links(
                self.grey(k), self.grey(l), k, l, self.models[k], self.models[l], self.lens,
                probes, self._probes[k], matcher,
            )  # fmt: skip
        return self._links[(k, l)]

    def forget_before(self, k: int) -> None:
        """Drop the links of frames before ``k`` (no later window needs them)."""
        for key in [key for key in self._links if key[1] < k]:
            del self._links[key]
        for key in [key for key in self._probes if key < k]:
            del self._probes[key]


def adjust_window(
    evidence: SequenceEvidence,
    window: Window,
    final: Mapping[int, PolyProjective],
    config: SequenceAdjustConfig,
) -> tuple[list[FrameAdjustment], dict[int, PolyProjective]]:
    """Solve one window with the final models before it held: the outcomes of the frames it
    makes final, in index order, and the window's solution for every frame it holds or
    solves."""
    steps = config.link_steps
    first = max(window.start - max(steps), 0)
    models: list[PolyProjective | None] = [None] * window.end
    for k in range(first, window.end):
        models[k] = final.get(k, evidence.models[k]) if k < window.start else evidence.models[k]
    held = {k for k in range(first, window.start) if models[k] is not None}
    held |= {k for k in evidence.fixed if first <= k < window.end and models[k] is not None}
    links = [
        evidence.links(k, k + s, config.probes, config.link_matcher)
        for s in steps
        for k in range(first, window.end - s)
        if k + s >= window.start and models[k] is not None and models[k + s] is not None
    ]
    solving = [
        k for k in range(window.start, window.end) if models[k] is not None and k not in held
    ]
    controls = [evidence.controls[k] for k in solving if evidence.controls[k] is not None]
    controls += [evidence.map_points[k].points for k in solving if k in evidence.map_points]
    priors = [_prior(k, models[k], evidence.outline, config.prior_sigma_px) for k in solving]
    out = adjust_models(
        models, links, controls, config.solver, fixed=held, priors=priors,
        report=range(window.start, window.final_end),
    )  # fmt: skip
    n_links = np.zeros(window.end, int)
    for lk in links:
        n_links[[lk.k, lk.l]] += len(lk.src_k)
    sigma_link = config.solver.link_sigma_px
    results = []
    for k in range(window.start, window.final_end):
        if models[k] is None:
            continue
        c = evidence.controls[k]
        control_rms = _finite(out.control_rms_px[k])
        link_rms = _finite(out.link_rms_px[k])
        position = _finite(out.position_sigma_px[k])
        if k in evidence.fixed and c is not None and len(c.src):
            control_rms, position = _own_fit(models[k], c)
        predicted = predicted_error(position, link_rms, sigma_link)
        mp = evidence.map_points.get(k)
        mp_rms = None if mp is None else _rms(out.models[k].apply(mp.points.src) - mp.points.dst)
        flagged = ""
        if predicted > config.flag_px:
            flagged = f"predicted error {predicted:.2f} px"
        elif n_links[k] == 0 and _has_neighbour(models, k, steps):
            flagged = "no links to its neighbours"
        elif mp_rms is not None and mp_rms > config.solver.f_scale * mp.points.sigma_px:
            flagged = f"its map points are {mp_rms:.1f} px from it"
        moved = 0.0
        if c is not None and len(c.src):
            moved = _rms(out.models[k].apply(c.src) - models[k].apply(c.src))
        results.append(FrameAdjustment(
            k, out.models[k], (window.start, window.end), int(n_links[k]),
            0 if c is None else len(c.src), link_rms, control_rms, position,
            round(predicted, 6), flagged, round(moved, 6),
            0 if mp is None else len(mp.points.src),
            None if mp_rms is None else round(mp_rms, 6), "" if mp is None else mp.note,
        ))  # fmt: skip
    solution = {k: out.models[k] for k in range(first, window.end) if out.models[k] is not None}
    return results, solution


def adjust_sequence(
    evidence: SequenceEvidence,
    config: SequenceAdjustConfig,
    final: Mapping[int, PolyProjective] | None = None,
) -> Iterator[tuple[FrameAdjustment, Mapping[int, PolyProjective]]]:
    """Every frame's :class:`FrameAdjustment`, window by window in index order (module
    docstring), each with the solution of the window that made it final (the models of its
    neighbours as that window saw them). ``final``: the models of frames already final (a
    resumed run): the windows they fill are skipped, and the next window holds them as they
    were."""
    final = dict(final or {})
    n = len(evidence.models)
    for window in window_plan(n, config):
        todo = [
            k for k in range(window.start, window.final_end)
            if evidence.models[k] is not None and k not in final
        ]  # fmt: skip
        if not todo:
            continue
        adjustments, solution = adjust_window(evidence, window, final, config)
        for adjusted in adjustments:
            final[adjusted.k] = adjusted.model
            if adjusted.k in todo:
                yield adjusted, solution
        evidence.forget_before(window.final_end - max(config.link_steps))


def _prior(k: int, model: PolyProjective, outline: NDArray, sigma_px: float) -> ControlPointSet:
    """Frame ``k``'s own model as a weak prior at the outline points it maps."""
    dst = model.apply(outline)
    ok = np.isfinite(dst).all(axis=1)
    return ControlPointSet(k, outline[ok], dst[ok], sigma_px)


# A homography's parameters: the fewest of any model a frame registered to the map keeps.
_HOMOGRAPHY_PARAMS = 8


def _own_fit(model: PolyProjective, c: ControlPointSet) -> tuple[float | None, float | None]:
    """``(control_rms_px, position_sigma_px)`` of a frame the adjustment holds (the reference
    frame): the RMS residual of its control points under its own model, and what that fit
    leaves unknown, the spread of a least-squares prediction at ``n`` points, RMS residual x
    sqrt(parameters / n), with a homography's 8 parameters (a richer model's is larger). Every
    frame hangs from it, so a reference frame whose own fit went wrong (28 control points 12.5
    px off their model, measured on a click-dragged fit) is flagged rather than held as
    exact."""
    rms = _rms(model.apply(c.src) - c.dst)
    return _finite(rms), _finite(rms * np.sqrt(min(_HOMOGRAPHY_PARAMS / len(c.src), 1.0)))


def _has_neighbour(models, k: int, steps) -> bool:
    return any(
        0 <= k + d < len(models) and models[k + d] is not None for s in steps for d in (-s, s)
    )


def _rms(d: NDArray) -> float:
    """RMS length of the ``(N, 2)`` vectors ``d``."""
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def _finite(v: float) -> float | None:
    return round(float(v), 6) if np.isfinite(v) else None
