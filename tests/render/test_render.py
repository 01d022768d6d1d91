"""Registered outputs: rendering into base pixels, footprints, field images, overlays, video."""

from __future__ import annotations

import json

import imageio.v2 as imageio
import numpy as np
import pytest

from registration import render
from registration.geometry import DisplacementField
from registration.io import read_image


def frame_image(w=120, h=90, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 255, size=(h, w, 3), dtype=np.uint8)


def test_render_registered_translation_is_exact():
    frame = frame_image()
    # Frame pixel q shows base point q + (40, 25).
    out, mask = render.render_registered(
        frame, lambda b: b - (40.0, 25.0), (200, 150), origin=(0, 0), return_mask=True
    )
    assert out.shape == (150, 200, 3)
    assert np.array_equal(out[25 : 25 + 90, 40 : 40 + 120], frame)
    assert mask[25:115, 40:160].all() and not mask[:24].any() and not mask[:, :39].any()
    assert (out[~mask] == 0).all()
    # A crop with an origin gives the same pixels.
    crop = render.render_registered(frame, lambda b: b - (40.0, 25.0), (50, 40), origin=(60, 30))
    assert np.array_equal(crop, out[30:70, 60:110])


def test_footprint_is_the_union_clipped_to_the_base():
    fns = [
        lambda q: q + (10.0, 20.0),
        lambda q: q + (50.0, -5.0),
        lambda q: np.full_like(q, np.nan),
    ]
    assert render.footprint(fns, (100, 80)) == (10, -5, 140, 105)
    assert render.footprint(fns, (100, 80), base_size=(120, 200)) == (10, 0, 110, 100)
    assert render.footprint([lambda q: np.full_like(q, np.nan)], (100, 80)) == (0, 0, 0, 0)


def test_field_component_images_colour_by_sign():
    vec = np.zeros((2, 3, 2), np.float32)
    vec[:, :, 0] = [[2, 2, 2], [2, 2, 2]]  # dx = +2 everywhere
    vec[:, :, 1] = [[-1, -1, -1], [-1, -1, -1]]  # dy = -1
    f = DisplacementField((50.0, 50.0), 100.0, vec, np.ones((2, 3), bool))
    u, v = render.field_component_images(f, 300, 200, limit_px=2.0, show_nodes=False)
    assert u.shape[0] == 200 and u.shape[1] > 300  # legend appended
    b, g, r = u[100, 150]
    assert r == 255 and b == 0  # +limit -> full red (BGR)
    b, g, r = v[100, 150]
    assert b == 255 and r < 140  # -limit/2 -> blue-ish
    u2, _ = render.field_component_images(f, 300, 200, legend=False, show_nodes=True)
    assert u2.shape == (200, 300, 3)
    assert (u2[50, 50] == 0).all()  # measured node drawn as a filled dot


def test_overlay_blends_where_the_frame_has_data():
    a = np.full((10, 10, 3), 200, np.uint8)
    b = np.full((10, 10), 100, np.uint8)
    mask = np.zeros((10, 10), bool)
    mask[:, :5] = True
    out = render.overlay(a, b, 0.5, mask=mask)
    assert (out[:, :5] == 150).all() and (out[:, 5:] == 100).all()
    with pytest.raises(ValueError, match="alpha"):
        render.overlay(a, b, 1.5)


def test_write_video_pads_to_even_size_and_is_atomic(tmp_path):
    frames = [np.full((75, 101, 3), 40 * k, np.uint8) for k in range(4)]
    out = render.write_video(iter(frames), tmp_path / "v.mp4", fps=5)
    assert out.is_file() and sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]
    reader = imageio.get_reader(str(out))
    got = [f for f in reader]
    reader.close()
    assert len(got) == 4 and got[0].shape == (76, 102, 3)
    assert abs(int(got[3][30, 50, 0]) - 120) < 6
    bad = [frames[0], np.zeros((80, 100, 3), np.uint8)]
    with pytest.raises(ValueError, match="video frame 1 is 100x80, the first was 101x75"):
        render.write_video(bad, tmp_path / "w.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


class Frames:
    def __init__(self, images):
        self.images = images

    def __len__(self):
        return len(self.images)

    def get(self, k):
        return self.images[k]


def test_write_registered_sequence(tmp_path):
    import cv2

    from registration import load

    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    meta = {
        "format": "aerialreg-result",
        "version": 1,
        "n_frames": 3,
        "gamma": 0.0,
        "frame_size": [120, 90],
        "base_size": [400, 300],
        "reference_frame": 0,
    }
    (out / "result.json").write_text(json.dumps(meta))
    images = [frame_image(seed=k) for k in range(3)]
    for k in range(3):
        rec = {"status": "ok" if k != 1 else "failed", "reason": "", "stats": {}}
        rec["model"] = {"type": "Translation", "params": [100.0 + 5 * k, 50.0]}
        (out / "frames" / f"{k:06d}.json").write_text(json.dumps(rec))
    field = DisplacementField(
        (100.0, 50.0), 100.0, np.zeros((1, 2, 2), np.float32), np.ones((1, 2), bool)
    )
    np.savez(
        out / "frames" / "000002.npz", **{f"field_{k}": v for k, v in field.to_arrays().items()}
    )
    cv2.imwrite(str(out / "mid_base.png"), np.zeros((300, 400, 3), np.uint8))
    info = render.write_registered_sequence(load(out), Frames(images))
    assert info["box"] == [98, 48, 134, 94]  # union of frames 0 and 2, padded by 2
    assert info["n_failed"] == 1
    d = out / "registered"
    assert sorted(p.name for p in (d / "frames").iterdir()) == [
        "000000.png",
        "000001.png",
        "000002.png",
    ]
    f0 = read_image(d / "frames" / "000000.png")
    assert np.array_equal(f0[2 : 2 + 90, 2 : 2 + 120], images[0])
    assert not read_image(d / "frames" / "000001.png").any()
    assert (d / "overlay" / "000002.jpg").is_file()
    assert (d / "field" / "000002_dx.png").is_file() and not (
        d / "field" / "000000_dx.png"
    ).exists()
    assert (d / "registered.mp4").stat().st_size > 0
