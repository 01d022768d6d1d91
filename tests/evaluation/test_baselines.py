"""The plain OpenCV baselines report a homography that cannot be a view of the frame as a failed
frame, not as a registration."""

from __future__ import annotations

import numpy as np

from registration.evaluation.baselines import BaselineResult, _without_degenerate, degenerate
from registration.lens import Camera

CAMERA = Camera(0.0, 640, 480)
# A view of the frame: turned 20 degrees, scaled 0.8, moved, with a little perspective.
_C, _S = np.cos(np.radians(20)) * 0.8, np.sin(np.radians(20)) * 0.8
GOOD = np.array([[_C, -_S, 900.0], [_S, _C, 400.0], [2e-5, -1e-5, 1.0]])


def test_a_view_of_the_frame_is_kept():
    assert not degenerate(GOOD, CAMERA)
    assert not degenerate(np.diag([-1.0, 1.0, 1.0]) @ GOOD, CAMERA)  # a mirrored map: one order


def test_collapsed_and_horizon_crossing_homographies_are_failures():
    # Rank 2 (what a chain to a reference frame the frame no longer sees multiplies into: the
    # long flight's last frames, their corners within 3 base px of each other).
    rank2 = GOOD.copy()
    rank2[1] = 0.5 * rank2[0] + 1e-12
    assert degenerate(rank2, CAMERA)
    # The horizon through the frame: two corners map behind the camera (the outline folds).
    horizon = GOOD.copy()
    horizon[2] = [-1.0 / 320.0, 0.0, 1.0]
    assert degenerate(horizon, CAMERA)
    assert degenerate(np.full((3, 3), np.nan), CAMERA)
    assert degenerate(None, CAMERA)


def test_degenerate_frames_become_failed_frames_by_index():
    rank2 = GOOD.copy()
    rank2[1] = 0.5 * rank2[0]
    res = BaselineResult(0.0, (640, 480), [GOOD, rank2, None, GOOD])
    out = _without_degenerate(res)
    assert [h is None for h in out.homographies] == [False, True, True, False]
    np.testing.assert_array_equal(out.homographies[3], GOOD)
