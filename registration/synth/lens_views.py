"""Raw frames that see a scene through a lens from two places (beyond the paper): the test
material of γ from motion (:mod:`registration.lens.gamma_from_motion`) on real photographs, whose scene is
exactly flat, so the matches between the two views obey one homography through the right lens."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from registration.geometry import remap
from registration.lens import RadialModel


def lens_pair(
    scene: NDArray,
    model: RadialModel,
    *,
    shift: float = 0.3,
    turn_deg: float = 8.0,
    cover: float = 0.7,
    max_zoom_out: float = 1.6,
    seed: int = 0,
) -> tuple[list[NDArray], list[NDArray[np.bool_]]]:
    """Two raw frames of ``model``'s size seeing ``scene`` (flat, undistorted) through the lens.

    The second view is moved by ``shift`` times the corrected frame's half width, in a seeded
    random direction, and turned by ``turn_deg``; the scale is chosen so that both views fit
    within ``cover`` of the scene. The corrected frame's extent is capped at ``max_zoom_out``
    times the raw frame's (near the validity limit the corners go to infinity).

    Returns:
        ``([raw_a, raw_b], [mask_a, mask_b])``: frames of ``scene``'s dtype and channels, and
        ``(H, W)`` bool masks of the raw pixels that see the scene.
    """
    rng = np.random.default_rng(seed)
    hs, ws = scene.shape[:2]
    w, h = int(model.width), int(model.height)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    corrected = model.corrected_from_raw(np.stack([xs.ravel(), ys.ravel()], 1)) - model.c
    half = np.array([w, h]) / 2.0
    extent = np.minimum(np.nanmax(np.abs(corrected), axis=0), max_zoom_out * half)
    scale = cover * min(ws / (2 * extent[0] * (1 + shift)), hs / (2 * extent[1] * (1 + shift)))
    direction = rng.uniform(0, 2 * np.pi)
    move = np.array([np.cos(direction), np.sin(direction)]) * shift * extent[0] * scale
    frames, masks = [], []
    for turn, offset in ((0.0, -move / 2), (np.deg2rad(turn_deg), move / 2)):
        rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]) * scale
        src = corrected @ rot.T + np.array([(ws - 1) / 2, (hs - 1) / 2]) + offset
        inside = (
            np.isfinite(src).all(1)
            & (src[:, 0] >= 1)
            & (src[:, 1] >= 1)
            & (src[:, 0] <= ws - 2)
            & (src[:, 1] <= hs - 2)
        )
        src[~inside] = np.nan
        frames.append(remap(scene, src.reshape(h, w, 2)))
        masks.append(inside.reshape(h, w))
    return frames, masks
