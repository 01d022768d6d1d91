"""The identity a result records of its frames: a frame replaced by another of the same size,
its modification time kept, is found (README "Reliability")."""

from __future__ import annotations

import os

import cv2
import numpy as np

from registration.io import frames_difference, open_frames


def _write(path, image) -> None:
    # PNG without compression: the file's size depends only on the image's size.
    assert cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 0])


def test_a_small_frame_replaced_at_the_same_size_and_mtime_is_found(tmp_path):
    """Frames of 32 KB, under the 2 x 64 KB a fingerprint samples: only the sample's hash can
    tell a replaced frame (the whole-file hash is only taken for larger files)."""
    rng = np.random.default_rng(5)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(3):
        _write(folder / f"{k:06d}.png", rng.integers(0, 255, (90, 120, 3), dtype=np.uint8))
    before = open_frames(folder).identity()
    target = folder / "000001.png"
    stat = target.stat()
    _write(target, rng.integers(0, 255, (90, 120, 3), dtype=np.uint8))
    os.utime(target, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert target.stat().st_size == stat.st_size < 128 * 1024
    frames = open_frames(folder)
    after = frames.identity()
    difference = frames_difference(before, after, [], frames)
    assert "frame 1" in difference and "content of its first or last 64 KB" in difference
    assert frames_difference(before, before, [], frames) == ""
