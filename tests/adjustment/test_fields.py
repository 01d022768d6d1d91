"""The local stage made consistent in time, against known truth: a frame's corrections on its
adjusted model are exact in the frame and bounded beyond it, and a frame without neighbours
keeps its own local stage; fields of frames that saw the same relief from nearly the same
place, each with its own matching noise, pool to the truth better than each alone; noise
without a common correction is shrunk away; a node only the frame itself measured keeps its
own correction."""

from __future__ import annotations

import numpy as np

from registration.adjustment import FrameField, consistent_field, correction_at
from registration.geometry import (
    DisplacementField,
    Normalisation,
    PolyProjective,
    Projective,
)

W, H = 640, 480
SPACING = 100.0


def _model(dx: float, dy: float, bend: float = 0.0) -> PolyProjective:
    """Frame px -> base px: a shift, with a little curvature."""
    proj = Projective.from_matrix(np.array([[1.0, 0, 200 + dx], [0, 1.0, 150 + dy], [0, 0, 1]]))
    corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float)
    poly = PolyProjective.from_projective(
        proj, 2, Normalisation.for_extent(W, H), Normalisation.from_points(proj.apply(corners))
    )
    p = poly.params.copy()
    p[0] += bend
    return poly.with_params(p)


def _field(vectors: np.ndarray, valid: np.ndarray | None = None) -> DisplacementField:
    gy, gx = vectors.shape[:2]
    return DisplacementField(
        (0.0, 0.0), SPACING, vectors.astype(np.float32),
        np.ones((gy, gx), bool) if valid is None else valid,
    )  # fmt: skip


def _clip(q):
    return np.c_[np.clip(q[:, 0], 0, W), np.clip(q[:, 1], 0, H)]


def _inside(q):
    return np.hypot(*(_clip(q) - q).T) < 1e-9


# The true correction (relief) on a 11 x 9 grid over the base: a bump of 1.5 px.
GX, GY = 11, 9
YY, XX = np.mgrid[0:GY, 0:GX]
RELIEF = np.stack(
    [1.5 * np.exp(-((XX - 5) ** 2 + (YY - 4) ** 2) / 4.0), 0.5 * np.sin(XX / 2.0)], -1
)


def test_corrections_on_the_adjusted_model_are_exact_and_a_lone_frame_keeps_its_own():
    own, adjusted = _model(0, 0), _model(0.4, -0.3, bend=0.0005)
    field_ = _field(RELIEF)
    frame = FrameField(field_, own, adjusted)
    assert consistent_field(frame, [], _clip) is None  # its local stage stays its own
    nodes = field_.node_xy.reshape(-1, 2)
    c, measured = correction_at(frame, nodes, _clip)
    q = own.inverse(nodes + field_.sample(nodes))
    inside = _inside(q)
    assert inside.sum() > 20 and (~inside).sum() > 20
    # In the frame: d'(x) = g'(q) - x, the adjusted model's view of the ground the own local
    # stage puts at x.
    np.testing.assert_allclose(c[inside], adjusted.apply(q[inside]) - nodes[inside], atol=1e-5)
    assert np.array_equal(measured, field_.valid.ravel() & inside)
    # Beyond it: the change of model at the frame's edge, not the two polynomials' extrapolation.
    qc = _clip(q[~inside])
    expected = field_.sample(nodes[~inside]) + adjusted.apply(qc) - own.apply(qc)
    np.testing.assert_allclose(c[~inside], expected, atol=1e-5)


def _covered(field_, model):
    nodes = field_.node_xy.reshape(-1, 2)
    q = model.inverse(nodes + field_.sample(nodes))
    return _inside(q).reshape(field_.shape)


def test_neighbours_fields_pool_to_the_truth_and_noise_alone_is_shrunk():
    rng = np.random.default_rng(7)
    frames = []
    for j in range(7):  # the same relief seen from 0.5 px apart, each with its own noise
        model = _model(0.5 * j, 0.0)
        noise = rng.normal(0, 0.3, RELIEF.shape)
        truth = RELIEF.copy()
        truth[:, 7:9] = 0.0  # columns 7-8: noise, no relief
        frames.append((FrameField(_field(truth + noise), model, model), truth))
    own, truth = frames[3]
    pooled = consistent_field(own, [f for i, (f, _) in enumerate(frames) if i != 3], _clip)
    ok = pooled.valid[::2, ::2] & _covered(own.field, own.own)
    assert ok.sum() >= 25
    # Own and adjusted models are one here: the frame's corrected field is its own plus delta.
    corrected = own.field.vectors + pooled.vectors[::2, ::2]
    err_own = np.hypot(*(own.field.vectors - truth)[ok].T)
    err_pooled = np.hypot(*(corrected - truth)[ok].T)
    # 7 frames: the noise drops by about sqrt(7).
    assert np.sqrt(np.mean(err_pooled**2)) < 0.55 * np.sqrt(np.mean(err_own**2))
    # Where there is no common correction, what is kept is smaller than one frame's noise.
    noise_only = ok.copy()
    noise_only[:, :7] = False
    noise_only[:, 9:] = False
    assert np.abs(corrected[noise_only]).mean() < 0.5 * np.abs(own.field.vectors[noise_only]).mean()


def test_a_node_only_the_frame_measured_keeps_its_own_correction():
    model = _model(0, 0)
    mine = _field(RELIEF)
    valid = np.ones((GY, GX), bool)
    valid[4, 5] = False  # the neighbour did not measure the bump's centre
    theirs = _field(RELIEF + 0.2, valid)
    pooled = consistent_field(
        FrameField(mine, model, model), [FrameField(theirs, model, model)], _clip
    )
    # Node (4, 5) of the own grid is not pooled (its correction comes from the pooled nodes
    # around it, which carry the neighbour's 0.2 px bias, halved); its neighbour node is.
    assert not pooled.valid[8, 10] and pooled.valid[8, 12]
    np.testing.assert_allclose(pooled.vectors[8, 10], [0.1, 0.1], atol=0.02)
    node = mine.node_xy[4, 5][None]
    _, measured = correction_at(FrameField(theirs, model, model), node, _clip)
    assert not measured[0]
