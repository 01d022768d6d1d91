"""The joint base of intra-sensor registration (paper 4.4): the mid base image, the previous
registered frame, and the base map where neither covers the frame.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.geometry import (
    PolyProjective,
)
from registration.global_registration.coarse_records import (
    CoarseConfig,
    CoarseFeatures,
    FrameView,
    coarse_features,
)
from registration.lens import Camera
from registration.matching import (
    Keypoints,
)
from registration.matching import grey as matching_grey


class DerivedCache:
    """What is computed from the mid base image once and shared by every frame (its coarse and
    full-scale SIFT, the local stage's keypoints and flow reference), dropped together when the
    image changes (:func:`add_to_mid_base`).

    Thread-safe: the local stages of several frames run at once (:mod:`registration.run.prefetch`);
    the first to ask for a value makes it, the others wait for it.
    """

    def __init__(self) -> None:
        self._values: dict[str, object] = {}
        self._lock = threading.RLock()

    def get(self, name: str, make: Callable[[], object]) -> object:
        """The value ``name``, made by ``make()`` the first time it is asked for."""
        with self._lock:
            if name not in self._values:
                self._values[name] = make()
            return self._values[name]

    def clear(self) -> None:
        with self._lock:
            self._values.clear()


@dataclass
class JointBase:
    """What intra-sensor registration matches a frame against (paper 4.4): the mid base image
    and the previously registered frame, with the base map for what neither covers.

    Attributes:
        mid_grey: the mid base image, grey, in base pixels (Hb, Wb); 0 where ``mid_valid`` is
            False.
        mid_valid: (Hb, Wb) bool, where the mid base image has content.
        mid_image: the mid base image as rendered (colour), for writing it out.
        base_grey, base_valid: the base map (grey) and its content mask, searched by the
            templates that neither the mid base image nor the previous frame can take
            (``IntraConfig.base_fallback``).
        previous: the previously registered frame, or None.
        previous_index: that frame's index in the sequence.
        derived: what is computed from the mid base image (:class:`DerivedCache`).
    """

    mid_grey: NDArray[np.uint8]
    mid_valid: NDArray[np.bool_]
    mid_image: NDArray[np.uint8] | None = None
    base_grey: NDArray[np.uint8] | None = None
    base_valid: NDArray[np.bool_] | None = None
    previous: PreviousFrame | None = None
    previous_index: int | None = None
    derived: DerivedCache = field(default_factory=DerivedCache, repr=False, compare=False)


@dataclass
class PreviousFrame:
    """The last registered frame: its view (image and pixel link), model and features.

    ``coarse`` (its coarse SIFT) and ``small`` (its grey at the coarse scale, for the fast
    path) are computed when first needed (:func:`previous_coarse`, :func:`previous_small`): a
    frame the fast path registers never needs its SIFT."""

    view: FrameView
    base_from_corrected: PolyProjective
    coarse: CoarseFeatures | None = None
    sift: Keypoints | None = None
    small: NDArray[np.uint8] | None = None


def previous_coarse(prev: PreviousFrame, ccfg: CoarseConfig) -> CoarseFeatures:
    """The previous frame's coarse SIFT (computed once) with the intra-sensor coarse settings
    ``ccfg`` (:func:`intra_coarse_config`)."""
    if prev.coarse is None:
        prev.coarse = coarse_features(prev.view.grey, ccfg, view=prev.view)
    return prev.coarse


def previous_small(prev: PreviousFrame, scale: float) -> NDArray[np.uint8]:
    """The previous frame's grey at ``scale`` (computed once)."""
    if prev.small is None:
        prev.small = matching_grey.downscale(prev.view.grey, scale)
    return prev.small


def make_joint_base(mid_base: NDArray, mid_valid: NDArray[np.bool_]) -> JointBase:
    """Prepare the mid base image for intra-sensor registration (computes its coarse SIFT once)."""
    grey = matching_grey.to_grey(mid_base)
    grey = np.where(mid_valid, grey, 0).astype(np.uint8)
    return JointBase(grey, mid_valid, mid_image=mid_base)


def mid_coarse(joint: JointBase, cfg: CoarseConfig) -> CoarseFeatures:
    """The mid base image's coarse SIFT (computed when first needed, after each change)."""
    return joint.derived.get(
        "mid_coarse", lambda: coarse_features(joint.mid_grey, cfg, mask=joint.mid_valid)
    )


def add_to_mid_base(joint: JointBase, image: NDArray, valid: NDArray[np.bool_], box) -> None:
    """Fill the mid base image's empty pixels inside ``box`` = ``(x0, y0, x1, y1)`` from
    ``image`` (a re-anchored frame rendered into that box, with its ``valid`` mask); content
    already there (the reference frame, earlier anchors) is kept, so a run's mid base image
    depends only on which frames were anchors and in which order. Its features and the prepared
    local-stage references are dropped (recomputed when next needed)."""
    x0, y0, x1, y1 = box
    hole = np.asarray(valid, bool) & ~joint.mid_valid[y0:y1, x0:x1]
    if not hole.any():
        return
    joint.mid_grey[y0:y1, x0:x1][hole] = matching_grey.to_grey(image)[hole]
    if joint.mid_image is not None:
        joint.mid_image[y0:y1, x0:x1][hole] = image[hole]
    joint.mid_valid[y0:y1, x0:x1] |= hole
    joint.derived.clear()


def mid_coverage(joint: JointBase, camera: Camera, model) -> float:
    """Share of the frame (a 16 x 12 grid of raw pixels) that ``model`` puts on content of the
    mid base image."""
    w, h = camera.size
    gx, gy = np.meshgrid((np.arange(16) + 0.5) * w / 16 - 0.5, (np.arange(12) + 0.5) * h / 12 - 0.5)
    b = model.apply(camera.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()]))
    hb, wb = joint.mid_valid.shape
    xi, yi = np.round(b[:, 0]), np.round(b[:, 1])
    ok = np.isfinite(b).all(axis=1) & (xi >= 0) & (xi < wb) & (yi >= 0) & (yi < hb)
    inside = np.zeros(len(b), bool)
    inside[ok] = joint.mid_valid[yi[ok].astype(int), xi[ok].astype(int)]
    return float(inside.mean())
