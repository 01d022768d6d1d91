"""The reference frame registered again through a lens beyond Harris (beyond the paper), when
:func:`registration.lens.estimate_k2` finds a significant fourth-order term.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from registration.geometry import Projective
from registration.global_registration.coarse_records import CoarseResult
from registration.global_registration.fine import FineConfig, FineResult, fine_register_reference
from registration.lens import Camera
from registration.lens.k2 import LensConfig, LensEstimate, estimate_k2


def register_with_lens(
    frame_raw: NDArray,
    base: NDArray,
    camera: Camera,
    coarse: CoarseResult,
    fine: FineResult,
    fine_cfg: FineConfig,
    config: LensConfig,
    *,
    match_in: str,
    base_valid: NDArray | None = None,
) -> tuple[Camera, FineResult, LensEstimate]:
    """The reference frame's fine step with the lens beyond Harris, when :func:`estimate_k2`
    finds one in ``fine``'s kept control points: ``(camera, fine, estimate)``, the camera with
    ``k2`` and the fine step run again with it (from a projective refitted to the same points
    in its corrected pixels: at the corners ``k2`` moves them by tens of px, beyond the
    templates' search), or ``camera`` and ``fine`` unchanged with the estimate saying why."""
    kept = fine.kept
    raw = camera.raw_from_corrected(fine.src[kept])
    estimate = estimate_k2(raw, fine.dst[kept], camera, config)
    if not estimate.adopted:
        return camera, fine, estimate
    lensed = camera.with_k2(estimate.k2)
    src, dst = lensed.corrected_from_raw(raw), fine.dst[kept]
    ok = np.isfinite(src).all(axis=1)
    start = Projective.estimate(src[ok], dst[ok])
    if start:
        start = Projective.estimate(src[ok], dst[ok], initial=start, optimizer="lm") or start
    again = None
    if start:
        moved = dataclasses.replace(coarse, base_from_corrected=start)
        again = fine_register_reference(
            frame_raw, base, lensed, moved, fine_cfg, match_in=match_in, base_valid=base_valid
        )
    if not again:
        why = again.reason if again is not None else "no projective fits the points"
        return camera, fine, estimate.refused(f"the fine step failed with it ({why}), Harris kept")
    return lensed, again, estimate
