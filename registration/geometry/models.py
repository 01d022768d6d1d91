"""Geometric models behind one protocol: translation, similarity, affine, projective and
polyprojective (paper eq. 5). The entry point for every caller: the protocol, failure object,
normalisation and optimisers live in :mod:`registration.geometry.estimation`, the projective and
polyprojective in :mod:`registration.geometry.rational` (fitted by :mod:`registration.geometry.rational_fit`),
and are re-exported here.

Every model maps ``(N, 2)`` float64 ``(x, y)`` pixel arrays to ``(N, 2)`` arrays and is named
target-first by its users (``base_from_frame``). Models are immutable (frozen dataclasses);
``with_params`` returns a new one.

The projective and polyprojective models work internally in *normalised* coordinates: a
similarity (:class:`Normalisation`) maps the source points' bounding box (or an image extent) to
about ``[-1, 1]`` and another one does the same for the destination. The normalisations are part
of the model, and ``params`` (what optimisers see) are the coefficients in normalised space, so
every coefficient is of order one and well conditioned, whatever the image size. ``apply`` and
``inverse`` convert from and to pixels.

Estimation (``Model.estimate``) returns the model or a falsy :class:`FailedEstimation` carrying a
reason (too few points, non-finite input, collinear or otherwise degenerate points). It starts
from a linear (normalised DLT) solution, or from ``initial``, and optionally refines the geometric
error (Euclidean distance in destination pixels) with Levenberg-Marquardt or Nelder-Mead.

References:
    Loveland & Rosten, "Acquisition and registration of aerial video imagery of urban traffic",
    section 4.3.2, eq. 5 (polyprojective / rational polynomial model).
    Hartley & Zisserman, "Multiple View Geometry", 2nd ed., algorithm 4.2 (normalised DLT).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from registration.geometry.estimation import (
    Chain,
    Inverted,
    Normalisation,
)
from registration.geometry.linear import Affine, Similarity, Translation
from registration.geometry.rational import PolyProjective, Projective

_TYPES: dict[str, type] = {
    "Translation": Translation,
    "Similarity": Similarity,
    "Affine": Affine,
    "Projective": Projective,
    "PolyProjective": PolyProjective,
    "Chain": Chain,
    "Inverted": Inverted,
}


def scale_at_frame_centre(model, to_corrected, width: int, height: int) -> float:
    """Base px per frame px of ``model`` (``base_from_corrected``) at the centre of a
    ``width`` x ``height`` frame, measured along its x axis; ``to_corrected`` maps the frame's
    pixels to corrected ones (``(N, 2)``)."""
    w, h = width, height
    c = to_corrected(np.array([[(w - 1) / 2, (h - 1) / 2], [(w - 1) / 2 + 10, (h - 1) / 2]]))
    b = model.apply(c)
    return float(np.hypot(*(b[1] - b[0])) / max(np.hypot(*(c[1] - c[0])), 1e-9))


def model_from_dict(d: dict[str, Any]) -> Any:
    """Restore a model written by ``to_dict()`` (JSON-able dict with a ``"type"`` key).

    Raises:
        ValueError: for an unknown type or missing keys, naming them.
    """
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError(f"model dict needs a 'type' key, got {d!r:.200}")
    kind = d["type"]
    try:
        if kind == "Translation":
            return Translation(np.asarray(d["params"], dtype=np.float64))
        if kind in ("Similarity", "Affine"):
            return _TYPES[kind](np.asarray(d["params"], dtype=np.float64))
        if kind == "Projective":
            return Projective(
                np.asarray(d["params"], dtype=np.float64),
                Normalisation.from_dict(d["src_norm"]),
                Normalisation.from_dict(d["dst_norm"]),
            )
        if kind == "PolyProjective":
            return PolyProjective(
                int(d["degree"]),
                np.asarray(d["params"], dtype=np.float64),
                Normalisation.from_dict(d["src_norm"]),
                Normalisation.from_dict(d["dst_norm"]),
            )
        if kind == "Chain":
            return Chain(model_from_dict(d["outer"]), model_from_dict(d["inner"]))
        if kind == "Inverted":
            return Inverted(model_from_dict(d["model"]))
    except KeyError as e:
        raise ValueError(f"model dict of type {kind!r} lacks key {e.args[0]!r}") from None
    raise ValueError(f"unknown model type {kind!r}; expected one of {sorted(_TYPES)}")


def _from_dict(cls: type, d: dict[str, Any]) -> Any:
    """Restore a model of this class from ``to_dict()`` output (see :func:`model_from_dict`)."""
    model = model_from_dict(d)
    if not isinstance(model, cls):
        raise ValueError(f"dict describes a {d.get('type')!r}, not a {cls.__name__}")
    return model


for _cls in (Translation, Similarity, Affine, Projective, PolyProjective, Chain, Inverted):
    _cls.from_dict = classmethod(_from_dict)  # type: ignore[attr-defined]
del _cls
