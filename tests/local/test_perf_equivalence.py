"""The faster forms of hot loops give what the plain forms give: the local stage's per-cell
counts and members."""

from __future__ import annotations

import cv2
import numpy as np

from registration.local.consensus import _box_counts, _cell_members


def test_box_counts_equal_an_integral_image():
    rng = np.random.default_rng(0)
    mask = rng.random((301, 407)) < 0.6
    cx = np.arange(-40.0, 450.0, 37.5)
    cy = np.arange(-25.0, 330.0, 41.0)
    half = 33.0
    got = _box_counts(mask, cx, cy, half)
    s = cv2.integral(mask.astype(np.uint8))
    h, w = mask.shape
    for i, y in enumerate(cy):
        for j, x in enumerate(cx):
            c0, c1 = (int(np.clip(np.floor(v + 0.5), 0, w)) for v in (x - half, x + half))
            r0, r1 = (int(np.clip(np.floor(v + 0.5), 0, h)) for v in (y - half, y + half))
            assert got[i, j] == s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0], (i, j)


def test_cell_members_equal_the_plain_selection():
    rng = np.random.default_rng(1)
    pos = rng.uniform(-20, 620, (3000, 2))
    pos[:50] = np.round(pos[:50] / 25) * 25  # samples exactly on cell edges
    cxs = 10.0 + 50.0 * np.arange(12)
    cys = 5.0 + 50.0 * np.arange(11)
    half = 50.0  # overlapping cells: a sample belongs to several
    usable = rng.random((11, 12)) < 0.8
    ii, jj, members = _cell_members(pos, cxs, cys, half, usable)
    assert list(zip(ii, jj, strict=True)) == list(zip(*np.nonzero(usable), strict=True))
    for c, (i, j) in enumerate(zip(ii, jj, strict=True)):
        inside = (
            (pos[:, 0] > cxs[j] - half)
            & (pos[:, 0] < cxs[j] + half)
            & (pos[:, 1] > cys[i] - half)
            & (pos[:, 1] < cys[i] + half)
        )
        want = np.flatnonzero(inside)  # ordered by index
        got = members[c][members[c] >= 0]
        np.testing.assert_array_equal(got, want)
