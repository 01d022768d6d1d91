"""An analyst's map points in the sequence adjustment (beyond the paper, whose one click seeds
the reference frame only): on any registered frame, a point of the frame and where it lies on the
map, one more constraint on that frame.

A map point is a control point of known noise (the precision of two clicks, not re-estimated
from residuals as a frame's own control points are: one point's residual says nothing about its
noise). Where the frame's own model disagrees with its map points by more than the solver's
robust scale (``f_scale`` noises), either the frame's own registration went wrong as a whole or
the click did, and the frame's image decides: its links to its neighbours are measured through
its own model and through the own model moved onto the map points (a translation for one point,
a similarity for more), and each model is judged by how far its links land from where the
neighbours' own models put them (a model the links cannot be found through is judged
wrong). Where the moved model agrees better, the frame's own control points, which agree with
each other and so would survive any robust loss, are set aside and the adjustment starts from
the moved model, so that its links are measured where its image shows its neighbours' ground.
Where the own model agrees better, it stays: the map points are one more constraint, and a
frame left far from them is flagged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.adjustment.solve import ControlPointSet
from registration.geometry import Normalisation, PolyProjective

DEFAULT_SIGMA_PX = 1.0
"""A map point's noise (base px) unless told: two clicks, each within a pixel or so."""


@dataclass(frozen=True)
class MapPoint:
    """Frame ``k``'s raw pixel ``frame_xy`` shows the ground at base pixel ``base_xy``
    (``sigma_px``: the point's noise, base px)."""

    k: int
    frame_xy: tuple[float, float]
    base_xy: tuple[float, float]
    sigma_px: float = DEFAULT_SIGMA_PX

    def __post_init__(self) -> None:
        values = (*self.frame_xy, *self.base_xy)
        if len(values) != 4 or not np.isfinite(values).all():
            raise ValueError(
                f"map point of frame {self.k}: coordinates must be finite x, y pairs, "
                f"got frame {self.frame_xy!r}, map {self.base_xy!r}"
            )
        if not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(
                f"map point of frame {self.k}: sigma_px must be > 0, got {self.sigma_px!r}"
            )
        object.__setattr__(self, "k", int(self.k))
        object.__setattr__(self, "frame_xy", (float(self.frame_xy[0]), float(self.frame_xy[1])))
        object.__setattr__(self, "base_xy", (float(self.base_xy[0]), float(self.base_xy[1])))
        object.__setattr__(self, "sigma_px", float(self.sigma_px))

    def to_json(self) -> dict:
        return {
            "frame": self.k,
            "frame_xy": list(self.frame_xy),
            "base_xy": list(self.base_xy),
            "sigma_px": self.sigma_px,
        }

    @classmethod
    def from_json(cls, obj: dict) -> MapPoint:
        return cls(
            int(obj["frame"]),
            tuple(obj["frame_xy"]),
            tuple(obj["base_xy"]),
            float(obj.get("sigma_px", DEFAULT_SIGMA_PX)),
        )


@dataclass(frozen=True)
class FrameMapPoints:
    """What a frame's map points make of its evidence (:func:`apply_map_points`).

    Attributes:
        start: the model the adjustment starts from and measures the frame's links through.
        controls: the frame's own control points, None where they were set aside.
        points: the map points as control points (corrected px -> base px, their noise).
        own_disagreement_px: the largest distance (base px) between a map point and where the
            frame's own model puts it.
        note: what the map points made of the frame's evidence: its own control points set
            aside, or its own model kept against them (``""``: they agree with it).
    """

    start: PolyProjective
    controls: ControlPointSet | None
    points: ControlPointSet
    own_disagreement_px: float
    note: str


def apply_map_points(
    k: int,
    model: PolyProjective,
    controls: ControlPointSet | None,
    src: NDArray,
    dst: NDArray,
    sigma_px: NDArray,
    f_scale: float,
    links_through: Callable[[PolyProjective], float] | None = None,
) -> FrameMapPoints:
    """Frame ``k``'s evidence (its own ``model`` and ``controls``) with its map points ``src``
    (corrected px, ``(N, 2)``) -> ``dst`` (base px), each of noise ``sigma_px`` (``(N,)``, base
    px); ``f_scale``: the solver's robust scale in noises; ``links_through(model)``: the median
    distance (base px) of the frame's links to its neighbours, measured through ``model``, from
    where the neighbours put them (inf where none is found; None: the map points are taken over
    the own model whenever they disagree). Module docstring."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    sigma = float(np.sqrt(np.mean(np.square(sigma_px))))
    points = ControlPointSet(k, src, dst, sigma, fixed_noise=True)
    off = np.hypot(*(model.apply(src) - dst).T)
    worst = float(np.max(off))
    if worst <= f_scale * sigma:
        return FrameMapPoints(model, controls, points, worst, "")
    start = moved_onto(model, similarity_onto(model.apply(src), dst))
    confirmed = ""
    if links_through is not None:
        own, moved = links_through(model), links_through(start)
        counts = (
            f"its links to its neighbours are {moved:.2f} base px off through them, "
            f"{own:.2f} through it"
        )
        if own < moved:
            note = (
                f"the analyst's map points are up to {worst:.1f} base px from its own "
                f"registration, which its image confirms ({counts}): it is kept"
            )
            return FrameMapPoints(model, controls, points, worst, note)
        confirmed = f", and its image confirms them ({counts})"
    note = (
        f"its own control points were set aside: the analyst's map points are up to "
        f"{worst:.1f} base px from where its own registration puts them{confirmed}"
    )
    return FrameMapPoints(start, None, points, worst, note)


def similarity_onto(p: NDArray, q: NDArray) -> NDArray:
    """The ``3 x 3`` similarity (no reflection) that moves points ``p`` onto ``q`` (``(N, 2)``)
    in least squares: a translation for one point."""
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    t = np.eye(3)
    if len(p) == 1:
        t[:2, 2] = q[0] - p[0]
        return t
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    # As complex numbers q - qc = a (p - pc): a = scale * exp(i angle), least squares.
    zp = (p - pc) @ np.array([1, 1j])
    zq = (q - qc) @ np.array([1, 1j])
    a = np.vdot(zp, zq) / max(np.vdot(zp, zp).real, 1e-12)
    t[:2, :2] = [[a.real, -a.imag], [a.imag, a.real]]
    t[:2, 2] = qc - t[:2, :2] @ pc
    return t


def moved_onto(model: PolyProjective, similarity: NDArray) -> PolyProjective:
    """``model`` followed by the base-px ``similarity`` (``3 x 3``), exactly: in the model's
    normalised output the similarity is a similarity too, and the rational model stays
    rational with the same denominator."""
    n: Normalisation = model.dst_norm
    c = np.asarray(n.center)
    lin = similarity[:2, :2]
    # y' = n(S(n^-1(y))) = lin y + (scale (S c - c)): n is x -> (x - c) scale.
    shift = n.scale * (lin @ c + similarity[:2, 2] - c)
    j = (model.degree + 1) * (model.degree + 2) // 2  # monomials: a, b of J, d of J - 1
    p = np.asarray(model.params, np.float64)
    a, b, d = p[:j], p[j : 2 * j], np.r_[p[2 * j :], 1.0]
    a2 = lin[0, 0] * a + lin[0, 1] * b + shift[0] * d
    b2 = lin[1, 0] * a + lin[1, 1] * b + shift[1] * d
    return PolyProjective(model.degree, np.r_[a2, b2, p[2 * j :]], model.src_norm, n)
