"""The local stage made consistent in time by the links, against known truth: frames whose own
local stages carry each its own smooth error are brought together where they see the same
ground, with their mean error kept (the links cannot know it) and not grown; frames that already
agree are left alone; a frame held at a known correction pulls its neighbour to it; wrong links
at named indices do not pull; a frame without links keeps its own local stage."""

from __future__ import annotations

import numpy as np
import pytest

from registration.adjustment import (
    FieldFrame,
    FieldSolveConfig,
    FrameLinks,
    solve_corrections,
)
from registration.geometry import DisplacementField

W, H = 400, 300
STEP = 40.0  # base px the camera moves between frames
SPACING = 50.0


def _offset(k: int) -> np.ndarray:
    return np.array([100.0 + STEP * k, 80.0])


def _error(k: int, rng_seed: int = 0):
    """Frame k's own local stage's error at base px ``x``: a smooth warp of its own (a shift,
    a tilt and a bend, up to ~1 px)."""
    rng = np.random.default_rng(1000 + 7 * k + rng_seed)
    a, b, c = rng.normal(0, 0.5, 2), rng.normal(0, 0.4, 2), rng.normal(0, 0.3, 2)

    def err(x):
        u = (x - _offset(k) - [W / 2, H / 2]) / [W / 2, H / 2]
        return a + b * u[:, :1] + c * (u[:, 1:2] ** 2)

    return err


def _frame(k: int, err, held_field=None, held=False) -> FieldFrame:
    """Truth: corrected px q -> base px q + offset; the own local stage adds ``err``."""

    def to_base(q):
        x = q + _offset(k)
        return x + err(x)

    grid = held_field
    if not held:
        ox, oy = _offset(k)
        gx, gy = int(W // SPACING) + 1, int(H // SPACING) + 1
        grid = DisplacementField(
            (ox, oy), SPACING, np.zeros((gy, gx, 2), np.float32), np.zeros((gy, gx), bool)
        )
    return FieldFrame(to_base, grid, held)


def _links(k: int, l: int, every: float = 20.0) -> FrameLinks:  # noqa: E741
    """Exact links: ground points both frames see, in each frame's corrected px."""
    lo = np.maximum(_offset(k), _offset(l)) + 10
    hi = np.minimum(_offset(k), _offset(l)) + [W - 10, H - 10]
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], every), np.arange(lo[1], hi[1], every))
    ground = np.c_[gx.ravel(), gy.ravel()]
    return FrameLinks(k, l, ground - _offset(k), ground - _offset(l))


def _corrected_error(frame: FieldFrame, delta: DisplacementField, k: int, ground):
    """Error against the truth of frame k's corrected local stage at ground points."""
    q = ground - _offset(k)
    x = frame.to_base(q)
    for _ in range(20):  # x' + δ(x') = own_local(q)
        x_new = frame.to_base(q) - delta.sample(x, outside="clamp")
        x = x_new
    return x - ground


def _ground(k: int, margin: float = 60.0):
    gx, gy = np.meshgrid(
        np.arange(margin, W - margin, 20.0) + _offset(k)[0],
        np.arange(margin, H - margin, 20.0) + _offset(k)[1],
    )
    return np.c_[gx.ravel(), gy.ravel()]


def _flight(n: int, links_of=_links):
    errors = {k: _error(k) for k in range(n)}
    frames = {k: _frame(k, errors[k]) for k in range(n)}
    links = [links_of(k, k + s) for s in (1, 2) for k in range(n - s)]
    return errors, frames, links


def test_frames_with_their_own_errors_are_brought_together_and_their_mean_error_kept():
    n = 8
    errors, frames, links = _flight(n)
    fields = solve_corrections(frames, links)
    assert set(fields) == set(range(n))
    before, after, mean_err, err_after = [], [], [], []
    for k in range(n - 1):
        ground = _ground(k)
        ground = ground[ground[:, 0] > _offset(k + 1)[0] + 60]  # seen by k and k+1
        e_k = _corrected_error(frames[k], fields[k], k, ground)
        e_l = _corrected_error(frames[k + 1], fields[k + 1], k + 1, ground)
        before.append(errors[k](ground) - errors[k + 1](ground))
        after.append(e_k - e_l)
        err_after.append(e_k)
        mean_err.append(np.mean([errors[j](ground) for j in range(n)], axis=0))
    rms = lambda a: float(np.sqrt(np.mean(np.sum(np.concatenate(a) ** 2, axis=1))))  # noqa: E731
    # Consecutive frames disagreed by ~1 px; the links bring them within a fraction of that.
    assert rms(before) > 0.5
    assert rms(after) < 0.2 * rms(before)
    # What all frames share the links cannot see: each corrected frame is near the frames'
    # mean error (a mean weighted by each frame's measured noise: measured 0.21 px from the
    # plain mean, where the frames were 0.83 px from the truth), and no further from the
    # truth than the frames were on average.
    assert rms([a - m for a, m in zip(err_after, mean_err, strict=True)]) < 0.3
    own = rms([errors[k](_ground(k)) for k in range(n)])
    assert rms(err_after) < own


def test_frames_that_already_agree_are_left_alone():
    n = 6

    def common(x):
        return np.c_[0.6 + 0 * x[:, 0], -0.4 + 0 * x[:, 1]]

    frames = {k: _frame(k, common) for k in range(n)}
    links = [_links(k, k + 1) for k in range(n - 1)]
    fields = solve_corrections(frames, links)
    for k in range(n):
        assert np.abs(fields[k].vectors).max() < 1e-6
        assert fields[k].valid.any()


def test_a_held_frame_pulls_its_neighbour_and_wrong_links_do_not():
    zero = lambda x: np.zeros_like(x)  # noqa: E731
    # Frame 0 held with a correction of +0.8 px in x (δ = -e = -0.8): its local stage is at
    # truth + 0.8 px; frame 1 is exact on its own and follows it where they overlap.
    held = DisplacementField(
        (0.0, 0.0), 1000.0, np.full((2, 2, 2), [-0.8, 0.0], np.float32), np.ones((2, 2), bool)
    )
    frames = {0: _frame(0, zero, held, held=True), 1: _frame(1, zero)}
    good = _links(0, 1)
    fields = solve_corrections(frames, [good])
    ground = _ground(1)
    ground = ground[ground[:, 0] < _offset(0)[0] + W - 80]
    e1 = _corrected_error(frames[1], fields[1], 1, ground)
    np.testing.assert_allclose(e1.mean(axis=0), [0.8, 0.0], atol=0.1)
    assert 0 not in fields  # held: not solved
    # The same with every fifth link 6 px wrong (cars, mismatches): the soft-L1 loss keeps the
    # solution within 0.15 px of the clean one.
    bad = good.src_l.copy()
    wrong = np.arange(0, len(bad), 5)
    bad[wrong] += [6.0, -6.0]
    fields_bad = solve_corrections(frames, [FrameLinks(0, 1, good.src_k, bad)])
    e1_bad = _corrected_error(frames[1], fields_bad[1], 1, ground)
    assert np.abs(e1_bad - e1).max() < 0.15
    # A plain least squares (one round, no reweighting) is pulled further by them.
    plain = solve_corrections(
        frames, [FrameLinks(0, 1, good.src_k, bad)], FieldSolveConfig(iterations=1)
    )
    e1_plain = _corrected_error(frames[1], plain[1], 1, ground)
    assert np.abs(e1_plain - e1).max() > 2 * np.abs(e1_bad - e1).max()


def test_frames_that_agree_within_noisy_links_are_held_where_they_are():
    # Exact local stages, links scattered by 0.3 px (the simulator's links are 0.2-0.6 px
    # from the truth while its local stage is within 0.1): the links' noise is measured and
    # nothing is moved by it.
    n = 8
    rng = np.random.default_rng(5)
    zero = lambda x: np.zeros_like(x)  # noqa: E731
    frames = {k: _frame(k, zero) for k in range(n)}
    links = []
    for s in (1, 2):
        for k in range(n - s):
            lk = _links(k, k + s)
            links.append(
                FrameLinks(k, k + s, lk.src_k, lk.src_l + rng.normal(0, 0.3, lk.src_l.shape))
            )
    fields = solve_corrections(frames, links)
    moved = max(np.abs(fields[k].vectors).max() for k in range(n))
    assert moved < 0.03, moved
    # The same links with the frames' noise assumed rather than measured (as if their local
    # stages were known to disagree by 0.5 px) move them by several times that.
    loose = solve_corrections(frames, links, FieldSolveConfig(min_sigma_px=0.5))
    assert max(np.abs(loose[k].vectors).max() for k in range(n)) > 3 * moved


def test_a_frame_without_links_keeps_its_own_local_stage():
    errors, frames, links = _flight(4)
    frames[9] = _frame(9, _error(9))
    fields = solve_corrections(frames, links)
    assert np.abs(fields[9].vectors).max() == 0.0 and not fields[9].valid.any()


@pytest.mark.parametrize(
    "name", ["prior_scale", "smooth_ratio", "min_sigma_px", "min_link_sigma_px"]
)
def test_the_noise_model_refuses_what_is_not_a_noise(name):
    with pytest.raises(ValueError, match=name):
        FieldSolveConfig(**{name: 0.0})


def test_a_kept_cache_of_link_pairs_gives_the_same_fields():
    """The caller's cache of each pair's points through the frames' own local stages (a
    sliding window meets most pairs twice) changes nothing: cold, warm and without it alike."""
    _, frames, links = _flight(8)
    plain = solve_corrections(frames, links)
    cache: dict = {}
    cold = solve_corrections(frames, links, cache=cache)
    assert set(cache) == {(lk.k, lk.l) for lk in links}
    warm = solve_corrections(frames, links, cache=cache)
    for k in plain:
        for other in (cold, warm):
            np.testing.assert_array_equal(other[k].vectors, plain[k].vectors)
            np.testing.assert_array_equal(other[k].valid, plain[k].valid)


def _disagreement(frames, fields, links) -> float:
    """RMS distance between two linked frames' corrected local stages at their common ground
    (base px), over ``links``; without ``fields``, their own local stages'."""
    out = []
    for lk in links:
        xs = []
        for j, src in ((lk.k, lk.src_k), (lk.l, lk.src_l)):
            x = frames[j].to_base(src)
            if fields is not None and j in fields:
                for _ in range(20):  # x' + δ(x') = own_local(q)
                    x = frames[j].to_base(src) - fields[j].sample(x, outside="clamp")
            xs.append(x)
        out.append(np.sum((xs[0] - xs[1]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(out))))


def test_frames_that_agree_only_in_twos_are_not_all_held():
    """Frames whose own local stages agree in twos (1 with 2, 3 with 4, ...; each two with an
    error of its own, up to ~1 px) and disagree with every other: every frame's best pair is
    within the links' noise. A window's typical noise read from its frames' best pairs (the
    rule before, here a quantile of 0) is then zero and every frame is held where it is; read
    from the lower quartile of all its pairs, the frames are brought together."""
    n = 9
    errors = {k: _error(k - 1 + k % 2) for k in range(1, n)}  # 1 and 2 share frame 1's
    zero = lambda x: np.zeros_like(x)  # noqa: E731
    held = DisplacementField(
        (0.0, 0.0), 1000.0, np.zeros((2, 2, 2), np.float32), np.ones((2, 2), bool)
    )
    frames = {0: _frame(0, zero, held, held=True)} | {k: _frame(k, errors[k]) for k in errors}
    links = [_links(k, k + s) for s in (1, 2, 3) for k in range(n - s)]
    own = _disagreement(frames, None, links)
    solved = _disagreement(frames, solve_corrections(frames, links), links)
    held_all = _disagreement(
        frames, solve_corrections(frames, links, FieldSolveConfig(typical_quantile=0.0)), links
    )
    assert held_all > 0.9 * own, (own, held_all)
    assert solved < 0.3 * own, (own, solved)


@pytest.mark.parametrize("q", [-0.1, 1.5, float("nan")])
def test_the_typical_quantile_must_be_a_quantile(q):
    with pytest.raises(ValueError, match="typical_quantile must be in"):
        FieldSolveConfig(typical_quantile=q)
