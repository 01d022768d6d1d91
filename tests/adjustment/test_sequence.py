"""The sequence adjustment window by window, against known truth: frames with exact
polyprojective models, control points with noise, links between frames (``link_steps``) with
noise; one frame registered 5 px off (its control points agree with its wrong model, as a frame
whose own registration went wrong), which the links contradict. Windows cover every frame once,
a resumed adjustment reaches the same models to the bit, the bad frame is flagged and does not
pull its neighbours, and the good frames are not flagged."""

from __future__ import annotations

import numpy as np
import pytest

from registration.adjustment import (
    ControlPointSet,
    FrameLinks,
    SequenceAdjustConfig,
    SequenceEvidence,
    adjust_sequence,
    window_plan,
)
from registration.geometry import Normalisation, PolyProjective, Projective

W, H = 640, 480
N = 14
BAD = 6  # this frame's own registration is 5 px off
CONFIG = SequenceAdjustConfig(window_frames=6, final_frames=3, link_steps=(1, 2))


def _truth(k: int) -> PolyProjective:
    a = np.deg2rad(1.5 * k)
    m = np.array([[np.cos(a), -np.sin(a), 300 + 30 * k], [np.sin(a), np.cos(a), 200], [0, 0, 1]])
    proj = Projective.from_matrix(m)
    corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float)
    poly = PolyProjective.from_projective(
        proj, 2, Normalisation.for_extent(W, H), Normalisation.from_points(proj.apply(corners))
    )
    p = poly.params.copy()
    p[0] += 0.002 * (1 + 0.1 * k)
    return poly.with_params(p)


def _grid(step: int = 40) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(20, W - 20, step, float), np.arange(20, H - 20, step, float))
    return np.c_[xs.ravel(), ys.ravel()]


def _fit(src, dst, like: PolyProjective) -> PolyProjective:
    """The frame's own registration: a polyprojective fitted to its control points."""
    model = PolyProjective.estimate(src, dst, initial=like, degree=2)
    assert model, model.reason
    return model


class _Evidence(SequenceEvidence):
    """Links from the truth with noise (no images to measure them from)."""

    def __init__(self, models, controls, truth, rng_seed: int) -> None:
        outline = np.array([[x, y] for x in (0, W / 2, W) for y in (0, H / 2, H)], float)
        super().__init__(models, controls, lambda k: None, None, outline, frozenset({0}))
        self.truth, self.rng_seed = truth, rng_seed
        self.measured: list[tuple[int, int]] = []

    def links(self, k, l, probes, matcher="flow"):  # noqa: E741
        rng = np.random.default_rng(self.rng_seed * 1000 + k * 31 + l)
        p = _grid(48) + rng.uniform(-5, 5, (1, 2))
        q = self.truth[l].inverse(self.truth[k].apply(p))
        inside = (q[:, 0] > 0) & (q[:, 0] < W) & (q[:, 1] > 0) & (q[:, 1] < H)
        self.measured.append((k, l))
        noise = rng.normal(0, 0.03, (int(inside.sum()), 2))
        return FrameLinks(k, l, p[inside], q[inside] + noise)


@pytest.fixture(scope="module")
def flight():
    rng = np.random.default_rng(5)
    truth = [_truth(k) for k in range(N)]
    models, controls = [], []
    for k in range(N):
        src = _grid() + rng.uniform(-3, 3, (1, 2))
        dst = truth[k].apply(src) + rng.normal(0, 0.3, (len(src), 2))
        if k == BAD:
            dst = dst + np.array([4.0, 3.0])  # the frame's own registration: 5 px off
        models.append(_fit(src, dst, truth[k]))
        controls.append(ControlPointSet(k, src, dst, 0.3))
    return truth, models, controls


def _error(model, truth) -> float:
    p = _grid(20)
    return float(np.mean(np.hypot(*(model.apply(p) - truth.apply(p)).T)))


def _run(flight, final=None):
    truth, models, controls = flight
    evidence = _Evidence(models, controls, truth, 1)
    return {a.k: a for a, _ in adjust_sequence(evidence, CONFIG, final)}, evidence


def test_windows_cover_every_frame_once_and_look_ahead():
    for n in (1, 5, 6, 7, 14, 100):
        windows = window_plan(n, CONFIG)
        finals = [k for w in windows for k in range(w.start, w.final_end)]
        assert finals == list(range(n))
        for w in windows[:-1]:
            assert w.end - w.final_end == CONFIG.window_frames - CONFIG.final_frames
        assert windows[-1].end == n


def test_adjustment_pulls_frames_together_and_the_bad_frame_is_flagged(flight):
    truth, models, _ = flight
    out, _ = _run(flight)
    assert sorted(out) == list(range(N))
    own = [_error(models[k], truth[k]) for k in range(N)]
    adjusted = [_error(out[k].model, truth[k]) for k in range(N)]
    assert own[BAD] > 4.5
    # The bad frame: its control points, which agree with each other, disagree with its links
    # as a whole; they weigh as their residuals show, and the links put the frame back.
    assert adjusted[BAD] < 0.1, adjusted[BAD]
    assert out[BAD].control_rms_px > 4.0
    # Its neighbours are not pulled towards it; every frame is within 0.1 px and says so.
    for k in range(N):
        assert adjusted[k] < 0.1, (k, own[k], adjusted[k])
        assert not out[k].flagged, (k, out[k].flagged)
        assert out[k].predicted_error_px < 0.1
    # Map evidence pooled over the window: the good frames' error drops (0.074 -> 0.043 px).
    good = [k for k in range(1, N) if k != BAD]
    assert np.mean([adjusted[k] for k in good]) < 0.7 * np.mean([own[k] for k in good])
    assert out[0].model is models[0]  # the reference frame is held


def test_a_frame_its_neighbours_cannot_be_found_in_is_flagged(flight):
    """Frame BAD's image shows another scene: no link to it survives."""
    truth, models, controls = flight

    class Blind(_Evidence):
        def links(self, k, l, probes, matcher="flow"):  # noqa: E741
            lk = super().links(k, l, probes, matcher)
            if BAD in (k, l):
                return FrameLinks(k, l, lk.src_k[:0], lk.src_l[:0])
            return lk

    out = {a.k: a for a, _ in adjust_sequence(Blind(models, controls, truth, 1), CONFIG)}
    assert out[BAD].flagged == "no links to its neighbours"
    assert out[BAD].n_links == 0
    assert [k for k in out if out[k].flagged] == [BAD]


def test_resumed_adjustment_equals_the_uninterrupted_one(flight):
    full, _ = _run(flight)
    # Stopped after the first two windows' frames (0..5) and frame 6 of the third: resumed
    # from their recorded models (a JSON round trip).
    from registration.geometry import model_from_dict

    done = {k: model_from_dict(full[k].model.to_dict()) for k in range(7)}
    resumed, evidence = _run(flight, done)
    assert sorted(resumed) == list(range(7, N))
    for k in resumed:
        assert np.array_equal(resumed[k].model.params, full[k].model.params), k
        assert resumed[k].to_dict() == full[k].to_dict()
    # The windows already final were not solved again (their links were never measured).
    assert min(k for k, _ in evidence.measured) >= 6 - max(CONFIG.link_steps)


@pytest.mark.parametrize(
    "changes",
    [
        {"final_frames": 0},
        {"final_frames": 50},
        {"link_steps": ()},
        {"link_steps": (0, 1)},
        {"link_steps": (40,)},
        {"flag_px": 0.0},
        {"prior_sigma_px": -1.0},
    ],
)
def test_config_refuses_bad_values(changes):
    with pytest.raises(ValueError, match=next(iter(changes)).split("_")[0]):
        SequenceAdjustConfig(**changes)


def test_a_reference_frame_whose_own_fit_went_wrong_is_flagged(flight):
    """The held reference frame (frame 0) is no unknown of the adjustment, but every frame
    hangs from it: its predicted error is what its own fit to the map leaves. With the
    flight's 165 control points at 0.3 px it is small; kept on 28 points 12 px off its model
    (a click-dragged fit: measured 28 points, RMS 12.5 px), it is flagged."""
    truth, models, controls = flight
    out, _ = _run(flight)
    assert out[0].control_rms_px < 0.5 and not out[0].flagged
    assert 0.05 < out[0].predicted_error_px < 0.1  # 0.42 px x sqrt(8 / 165)
    rng = np.random.default_rng(8)
    src = controls[0].src[:28]
    dst = models[0].apply(src) + rng.normal(0, 12.0 / np.sqrt(2), (28, 2))
    dragged = [ControlPointSet(0, src, dst, 1.9), *controls[1:]]
    out = {a.k: a for a, _ in adjust_sequence(_Evidence(models, dragged, truth, 1), CONFIG)}
    assert out[0].control_rms_px > 10
    assert out[0].predicted_error_px > CONFIG.flag_px
    assert out[0].flagged.startswith("predicted error"), out[0].flagged
