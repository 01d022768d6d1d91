"""The flyover benchmark's paired comparison of map agreement (adjusted against each frame
alone), on scores of known differences."""

from __future__ import annotations

import numpy as np

from benchmarks.flyover import paired_difference


def test_paired_difference_compares_the_frames_both_scored():
    rng = np.random.default_rng(3)
    reference = {
        k: float(v) for k, v in zip(range(0, 600, 10), rng.uniform(0.3, 0.5, 60), strict=True)
    }
    shift = {k: (-0.02 if i < 15 else 0.02 if i < 20 else 0.001) for i, k in enumerate(reference)}
    scores = {k: reference[k] + shift[k] for k in reference}
    scores[605] = 0.9  # scored in one run only: left out
    p = paired_difference(scores, reference)
    assert p["n_frames"] == 60
    assert np.isclose(p["median"], 0.001)
    assert np.isclose(p["mean"], (15 * -0.02 + 5 * 0.02 + 40 * 0.001) / 60)
    assert 0 < p["mean_se"] < 0.01
    assert p["ci95"][0] <= p["median"] <= p["ci95"][1]
    assert (p["n_lower"], p["n_higher"]) == (15, 5)
    assert paired_difference(scores, {}) is None
    assert paired_difference(scores, reference) == p  # seeded: the same interval again
