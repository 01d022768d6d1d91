"""Re-anchored frames fill the mid base image only from their centre
(``IntraConfig.anchor_fill_radius``), checked against a known model and lens."""

from __future__ import annotations

import numpy as np
import pytest

from registration.geometry import Similarity
from registration.global_registration import IntraConfig, JointBase
from registration.lens import Camera
from registration.run import render_anchor

W, H = 160, 120
BASE = (600, 450)


def _joint(filled_box=None) -> JointBase:
    wb, hb = BASE
    grey = np.zeros((hb, wb), np.uint8)
    valid = np.zeros((hb, wb), bool)
    if filled_box is not None:
        x0, y0, x1, y1 = filled_box
        grey[y0:y1, x0:x1] = 7
        valid[y0:y1, x0:x1] = True
    return JointBase(mid_grey=grey, mid_valid=valid)


def _scene():
    camera = Camera(gamma=0.5, width=W, height=H)
    # base = 1.5 * rotate(20°) * corrected + t: the frame lies inside the base, its centre at
    # (300, 225).
    a = np.deg2rad(20.0)
    c, s = 1.5 * np.cos(a), 1.5 * np.sin(a)
    centre = camera.corrected_from_raw(np.array([[(W - 1) / 2, (H - 1) / 2]]))[0]
    t = np.array([300.0, 225.0]) - np.array([[c, -s], [s, c]]) @ centre
    model = Similarity.from_matrix([[c, -s, t[0]], [s, c, t[1]], [0, 0, 1]])
    rng = np.random.default_rng(3)
    frame = rng.integers(20, 236, (H, W), dtype=np.uint8)
    return camera, model, frame


def _raw_radius_of_filled(joint, camera, model) -> np.ndarray:
    """The exact raw radius of each filled base pixel; NaN for those within 2 raw px of the
    frame's border, where the renderer's mapping (exact on a lattice 8 px apart, interpolated in
    between) may take its value from across the footprint's edge."""
    ys, xs = np.nonzero(joint.mid_valid)
    raw = camera.raw_from_corrected(model.inverse(np.c_[xs, ys].astype(float)))
    inner = (raw >= 2).all(axis=1) & (raw[:, 0] <= W - 3) & (raw[:, 1] <= H - 3)
    r = np.hypot(raw[:, 0] - (W - 1) / 2, raw[:, 1] - (H - 1) / 2) / (np.hypot(W, H) / 2)
    return np.where(inner, r, np.nan)


@pytest.mark.parametrize("radius", [0.5, 0.7])
def test_an_anchor_fills_only_within_its_fill_radius(radius):
    camera, model, frame = _scene()
    whole, centre = _joint(), _joint()
    render_anchor(whole, frame, camera, model, None)
    render_anchor(centre, frame, camera, model, None, fill_radius=radius)
    r_whole = _raw_radius_of_filled(whole, camera, model)
    r_centre = _raw_radius_of_filled(centre, camera, model)
    assert np.nanmax(r_whole) > 0.95  # the whole frame reaches its corners
    # Every filled base pixel comes from within the radius (one raw px of interpolation slack),
    # and all of the frame within it, less a px, is there.
    px = 1.0 / (np.hypot(W, H) / 2)
    assert np.nanmax(r_centre) < radius + px, np.nanmax(r_centre)
    inside = r_whole < radius - px
    ys, xs = np.nonzero(whole.mid_valid)
    assert centre.mid_valid[ys[inside], xs[inside]].all()
    # What it fills is the frame's own content, as the whole-frame rendering has it.
    assert np.array_equal(centre.mid_grey[centre.mid_valid], whole.mid_grey[centre.mid_valid])


def test_an_anchor_keeps_what_the_mid_base_image_had():
    camera, model, frame = _scene()
    joint = _joint(filled_box=(280, 205, 320, 245))
    render_anchor(joint, frame, camera, model, None, fill_radius=0.7)
    assert (joint.mid_grey[205:245, 280:320] == 7).all()
    assert joint.mid_valid.sum() > 40 * 40


@pytest.mark.parametrize("radius", [0.0, -0.2, 1.5])
def test_fill_radius_outside_its_range_is_refused_by_name(radius):
    with pytest.raises(ValueError, match=rf"anchor_fill_radius must be in \(0, 1\].*{radius}"):
        IntraConfig(anchor_fill_radius=radius)
