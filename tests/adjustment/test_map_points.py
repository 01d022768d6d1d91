"""An analyst's map points in the adjustment (:mod:`registration.adjustment.map_points`),
against known transforms: the own model moved onto them exactly, the similarity recovered, a
frame's own control points kept where they agree with its map points and set aside where they
do not."""

from __future__ import annotations

import numpy as np
import pytest

from registration.adjustment import (
    ControlPointSet,
    MapPoint,
    apply_map_points,
    moved_onto,
    similarity_onto,
)
from registration.geometry import Normalisation, PolyProjective, Projective


def _model(seed: int = 0) -> PolyProjective:
    """A degree-2 polyprojective from corrected px of a 640 x 480 frame to base px, with
    second-order terms (as a fine step leaves it)."""
    rng = np.random.default_rng(seed)
    h = np.array([[1.2, 0.1, 300.0], [-0.08, 1.15, 200.0], [2e-5, -1e-5, 1.0]])
    proj = Projective.from_matrix(h)
    corners = np.array([[0, 0], [640, 0], [640, 480], [0, 480]], float)
    m = PolyProjective.from_projective(
        proj, 2, Normalisation.for_extent(640, 480), Normalisation.from_points(proj.apply(corners))
    )
    p = np.array(m.params)
    p[:3] += rng.normal(0, 0.01, 3)  # bend: the quadratic terms of a
    p[6:9] += rng.normal(0, 0.01, 3)
    return PolyProjective(2, p, m.src_norm, m.dst_norm)


def _similarity(scale: float, angle_deg: float, t) -> np.ndarray:
    a = np.radians(angle_deg)
    s = np.eye(3)
    s[:2, :2] = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    s[:2, 2] = t
    return s


def _apply(s: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ s[:2, :2].T + s[:2, 2]


def test_moved_onto_is_the_model_followed_by_the_similarity_exactly():
    model = _model()
    s = _similarity(1.03, 4.0, (25.0, -12.0))
    xy = np.random.default_rng(1).uniform([0, 0], [640, 480], (200, 2))
    moved = moved_onto(model, s)
    np.testing.assert_allclose(moved.apply(xy), _apply(s, model.apply(xy)), atol=1e-8)


@pytest.mark.parametrize("n", [1, 2, 5])
def test_similarity_onto_recovers_a_known_similarity(n):
    p = np.random.default_rng(2).uniform(0, 1000, (n, 2))
    s = _similarity(0.97, -7.0, (40.0, 15.0)) if n > 1 else _similarity(1, 0, (40.0, 15.0))
    np.testing.assert_allclose(similarity_onto(p, _apply(s, p)), s, atol=1e-9)


def _controls(model, k=3, offset=(0.0, 0.0)):
    src = np.random.default_rng(3).uniform([20, 20], [620, 460], (60, 2))
    return ControlPointSet(k, src, model.apply(src) + offset, 0.3)


def test_map_points_that_agree_keep_the_frames_own_control_points():
    model = _model()
    controls = _controls(model)
    src = np.array([[100.0, 120.0], [500.0, 380.0]])
    dst = model.apply(src) + [1.5, -1.0]  # within 3 noises of 1 px
    mp = apply_map_points(3, model, controls, src, dst, np.ones(2), 3.0)
    assert mp.controls is controls and mp.start is model and mp.note == ""
    assert mp.points.k == 3 and mp.points.fixed_noise and mp.points.sigma_px == 1.0
    assert mp.own_disagreement_px == pytest.approx(np.hypot(1.5, 1.0))


def test_map_points_that_disagree_set_the_own_control_points_aside_and_move_the_start():
    """A frame registered 30 base px off (its model and control points moved together): two
    map points at the truth put its starting model back within their own noise."""
    truth = _model()
    off = _similarity(1.0, 0.0, (24.0, 18.0))
    wrong = moved_onto(truth, off)
    src = np.array([[100.0, 120.0], [500.0, 380.0]])
    dst = truth.apply(src)
    mp = apply_map_points(3, wrong, _controls(wrong), src, dst, np.ones(2), 3.0)
    assert mp.controls is None
    assert mp.own_disagreement_px == pytest.approx(30.0)
    assert "set aside" in mp.note and "30.0 base px" in mp.note
    grid = np.random.default_rng(4).uniform([0, 0], [640, 480], (100, 2))
    assert np.max(np.hypot(*(mp.start.apply(grid) - truth.apply(grid)).T)) < 1e-6


@pytest.mark.parametrize("own_links, moved_links", [(0.3, 30.0), (np.inf, 0.3)])
def test_the_frames_image_decides_between_its_own_model_and_its_map_points(own_links, moved_links):
    """Map points 30 px from the own model: the model its links to its neighbours agree with
    is kept (a mis-click is then one more constraint, and the frame stays), else the map
    points'."""
    truth = _model()
    wrong = moved_onto(truth, _similarity(1.0, 0.0, (24.0, 18.0)))
    src = np.array([[100.0, 120.0]])
    controls = _controls(wrong)

    def links_through(model) -> float:
        return own_links if model is wrong else moved_links

    mp = apply_map_points(3, wrong, controls, src, truth.apply(src), np.ones(1), 3.0, links_through)
    if own_links < moved_links:
        assert mp.start is wrong and mp.controls is controls
        assert (
            "which its image confirms (its links to its neighbours are 30.00 base px off "
            "through them, 0.30 through it): it is kept" in mp.note
        )
    else:
        assert mp.controls is None
        assert np.allclose(mp.start.apply(src), truth.apply(src), atol=1e-6)
        assert "set aside" in mp.note
        assert (
            "its image confirms them (its links to its neighbours are 0.30 base px off "
            "through them, inf through it)" in mp.note
        )


def test_map_point_records_refuse_non_finite_values():
    with pytest.raises(ValueError, match=r"map point of frame 2: coordinates must be finite"):
        MapPoint(2, (np.nan, 3.0), (1.0, 2.0))
    with pytest.raises(ValueError, match=r"sigma_px must be > 0, got 0"):
        MapPoint(2, (1.0, 3.0), (1.0, 2.0), 0)
    p = MapPoint(2, (1, 3), (4, 5), 0.5)
    assert MapPoint.from_json(p.to_json()) == p
