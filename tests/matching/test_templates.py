"""Tests for registration.matching.templates: the template grid, normalised cross-correlation with a
sub-pixel and dithered peak, the structure anchor, the second reference, and the gradient
signal, against known warps of synthetic and real images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from registration.io import read_image
from registration.matching import (
    ControlPoints,
    Reference,
    TemplateConfig,
    subpixel_peak,
    template_control_points,
    template_grid,
    to_grey,
)
from registration.run import CHANGE_LOG_RATIO
from tests.matching.test_features import (
    bent_warp,
    coarse_model,
    fourier_shift,
    real_grey,
    texture,
    warp_into,
)


def _template_recovery(ref: np.ndarray, frame_size) -> ControlPoints:
    ref_size = (ref.shape[1], ref.shape[0])
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    # The coarse model is several px off the truth.
    grid = template_grid(*frame_size).astype(float)
    assert np.median(np.linalg.norm(coarse(grid) - truth(grid), axis=1)) > 2.5
    cp = template_control_points(frame, ref, coarse, coarse_inv, TemplateConfig())
    err = np.linalg.norm(cp.dst - truth(cp.src), axis=1)
    assert len(cp) > 0.8 * len(grid)
    assert np.median(err) < 0.2, f"median error {np.median(err):.3f} px"
    assert (cp.score >= 0.5).all()
    return cp


def test_subpixel_peak_recovers_fractional_shift():
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.normal(size=(160, 160)).astype(np.float32), (0, 0), 2.0)
    for dx, dy in [(0.3, -0.45), (-0.2, 0.15), (0.49, 0.0)]:
        shifted = fourier_shift(img, dx, dy)
        tpl = img[43:118, 43:118]  # 75 x 75 around (80, 80)
        window = shifted[33:128, 33:128]  # +-10 px search
        res = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED)
        _, _, _, (px, py) = cv2.minMaxLoc(res)
        for method in ("quadratic", "parabolic"):
            off = (
                np.array([px, py])
                - 10
                + subpixel_peak(res[py - 1 : py + 2, px - 1 : px + 2], method)[0]
            )
            np.testing.assert_allclose(off, [dx, dy], atol=0.1, err_msg=method)
    # An exact quadratic surface is recovered exactly.
    u = np.arange(-1, 2)
    x, y = np.meshgrid(u, u)
    surface = -((x - 0.3) ** 2) - 2 * (y + 0.2) ** 2 + 0.5 * (x - 0.3) * (y + 0.2)
    np.testing.assert_allclose(subpixel_peak(surface, "quadratic")[0], [0.3, -0.2], atol=1e-9)
    assert subpixel_peak(surface, "none")[0].tolist() == [0.0, 0.0]


def test_template_control_points_recover_known_warp_texture():
    _template_recovery(texture(700, 560, seed=2), (460, 340))


def test_template_control_points_recover_known_warp_real():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)  # 960x540
    _template_recovery(ref, (560, 360))


def test_template_direct_correlation_paper_mode():
    # Without the reference warp (paper 4.3.2) a pure translation is recovered exactly.
    ref = texture(400, 320, seed=3)
    shift = np.array([40 + 3.4, 40 - 2.7])
    frame = warp_into(ref, lambda xy: xy + shift, 300, 240)
    guess = np.array([41.0, 41.0])  # the coarse model, 3-4 px off
    for cfg in (TemplateConfig(warp_reference=False), TemplateConfig.paper()):
        cp = template_control_points(frame, ref, lambda xy: xy + guess, lambda xy: xy - guess, cfg)
        assert len(cp) == len(template_grid(300, 240, cfg))
        assert np.median(np.linalg.norm(cp.dst - (cp.src + shift), axis=1)) < 0.1


def test_dithered_correlation_reduces_subpixel_bias():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)
    shift = np.array([3.3, -2.6])  # fractional: the plain peak fit is biased here
    frame = warp_into(ref, lambda xy: xy + shift + 100, 560, 340)
    model = lambda xy: xy + 100.0  # noqa: E731
    errs = []
    for n in (0, 1):
        cp = template_control_points(frame, ref, model, None, TemplateConfig(dither_iterations=n))
        errs.append(np.percentile(np.linalg.norm(cp.dst - (cp.src + shift + 100), axis=1), 90))
    assert errs[1] < 0.15 and errs[1] < 0.7 * errs[0], errs


def test_dithered_correlation_reduces_subpixel_bias_simulated(sim_seq):
    """Synthetic twin of the test above (runs without ../shared): a simulated frame shifted by an
    exact band-limited (Fourier) shift of half a pixel in x and y, where the plain peak fit is
    most biased; the dithered re-correlation halves the 90th percentile error (measured 0.054 ->
    0.028 px, median 0.030 -> 0.013). The shift is not made with ``cv2.remap``: its 1/32 px
    position quantum differs between OpenCV builds and is itself of this size."""
    ref = to_grey(read_image(sim_seq / "frames" / "000000.png"))
    shift = np.array([3.5, -2.5])
    h, w = ref.shape
    frame = fourier_shift(ref, -shift[0], -shift[1])[40 : h - 40, 40 : w - 40]
    model = lambda xy: xy + 40.0  # noqa: E731
    errs = []
    for n in (0, 1):
        cp = template_control_points(frame, ref, model, None, TemplateConfig(dither_iterations=n))
        assert len(cp) >= 50
        errs.append(np.percentile(np.linalg.norm(cp.dst - (cp.src + shift + 40), axis=1), 90))
    assert errs[1] < 0.028 * 1.3 and errs[1] < 0.6 * errs[0], errs


def test_template_grid_and_jitter():
    cfg = TemplateConfig()
    grid = template_grid(400, 300, cfg)
    assert len(grid) == 7 * 5
    assert (np.diff(np.unique(grid[:, 0])) == 50).all()
    assert grid[:, 0].min() >= 37 and grid[:, 0].max() <= 400 - 38
    d = TemplateConfig(jitter_px=12.5, jitter_seed=4)
    g1, g2 = template_grid(400, 300, d), template_grid(400, 300, d)
    np.testing.assert_array_equal(g1, g2)  # reproducible
    assert np.abs(g1 - grid).max() <= 12 and (g1 != grid).any()
    assert (g1 >= 37).all() and (g1[:, 0] <= 362).all() and (g1[:, 1] <= 262).all()
    assert (template_grid(400, 300, TemplateConfig(jitter_px=12.5, jitter_seed=5)) != g1).any()
    assert len(template_grid(60, 300, cfg)) == 0  # narrower than one template


def test_jittered_templates_still_recover_warp():
    ref = texture(700, 560, seed=2)
    ref_size, frame_size = (700, 560), (460, 340)
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    cfg = TemplateConfig(jitter_px=12.5, anchor="centre")
    cp = template_control_points(frame, ref, coarse, coarse_inv, cfg)
    grid = template_grid(*frame_size, cfg)
    assert {tuple(p) for p in cp.src.astype(int)} <= {tuple(p) for p in grid}
    assert np.median(np.linalg.norm(cp.dst - truth(cp.src), axis=1)) < 0.2


def test_structure_anchor_follows_the_texture_and_reduces_error():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)
    ref_size, frame_size = (ref.shape[1], ref.shape[0]), (560, 360)
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    med = {}
    for anchor in ("centre", "structure"):
        cp = template_control_points(frame, ref, coarse, coarse_inv, TemplateConfig(anchor=anchor))
        med[anchor] = np.median(np.linalg.norm(cp.dst - truth(cp.src), axis=1))
        on_grid = np.isin(cp.src, template_grid(*frame_size)).all()
        assert on_grid == (anchor == "centre")
    assert med["structure"] < 0.9 * med["centre"], med


def test_structure_anchor_moves_to_the_textured_side():
    """A frame textured only right of x = 200: templates straddling it anchor right of their
    centre, where the texture that carries the match is (runs without ../shared)."""
    tex = texture(400, 200, seed=8)
    tex[:, :200] = 128
    model = lambda xy: xy + 0.0  # noqa: E731
    cp = template_control_points(tex, tex, model, model, TemplateConfig())
    centres = template_grid(400, 200)
    nearest = centres[np.argmin(np.linalg.norm(cp.src[:, None] - centres[None], axis=2), axis=1)]
    straddling = nearest[:, 0] - 37 < 200  # template's left part is flat
    assert straddling.sum() >= 2
    assert (cp.src[straddling, 0] - nearest[straddling, 0] > 5).all()
    np.testing.assert_allclose(cp.dst, cp.src, atol=0.05)


def test_texture_check_skips_flat_templates():
    ref = texture(500, 400, seed=4)
    ref[:, 250:] = 120  # flat right half (asphalt, roof)
    ref[:, 250:] += np.random.default_rng(1).integers(
        0, 2, (400, 250), dtype=np.uint8
    )  # faint noise
    frame = ref[40:360, 40:460].copy()
    model, inverse = (lambda xy: xy + 40.0), (lambda xy: xy - 40.0)
    cp = template_control_points(frame, ref, model, inverse, TemplateConfig())
    assert len(cp) > 0
    # Every kept template lies (with its 75 px extent) at least partly on the textured half.
    assert (cp.src[:, 0] + 40 - 37 < 250).all()
    np.testing.assert_allclose(cp.dst, cp.src + 40.0, atol=0.1)
    loose = template_control_points(
        frame, ref, model, inverse, TemplateConfig(min_template_std=0, min_score=-1)
    )
    assert len(loose) > len(cp)


def test_template_empty_and_flat_inputs_give_empty_control_points():
    flat = np.full((300, 400), 77, np.uint8)
    ref = texture(400, 300)
    ident = lambda xy: xy  # noqa: E731
    for frame, reference in [(flat, ref), (ref, flat), (flat, flat), (ref[:50, :50], ref)]:
        cp = template_control_points(frame, reference, ident, ident, TemplateConfig())
        assert isinstance(cp, ControlPoints) and len(cp) == 0
        assert cp.src.shape == (0, 2) and cp.dst.shape == (0, 2)
    # A model sending everything outside the reference, or to NaN.
    far = lambda xy: xy + 10_000.0  # noqa: E731
    assert len(template_control_points(ref, ref, far, None, TemplateConfig())) == 0
    nan = lambda xy: np.full_like(xy, np.nan)  # noqa: E731
    assert len(template_control_points(ref, ref, nan, None, TemplateConfig())) == 0
    with pytest.raises(ValueError, match="ref_from_frame"):
        template_control_points(ref, ref, lambda xy: xy[:, :1], None, TemplateConfig())
    with pytest.raises(ValueError, match="subpixel"):
        TemplateConfig(subpixel="cubic")
    with pytest.raises(ValueError, match="anchor"):
        TemplateConfig(anchor="corner")


def test_templates_fall_back_to_a_second_reference_where_the_first_has_no_content():
    """Templates whose search window touches the first reference's empty part are searched in the
    fallback; each point names its reference and its dst is in that reference's pixels."""
    frame = texture(480, 360, seed=21)
    t_ref, t_fb = np.array([30.4, -12.7]), np.array([-8.2, 5.6])
    ref = warp_into(frame, lambda xy: xy - t_ref, 560, 420)  # ref(x) = frame(x - t_ref)
    fb = warp_into(frame, lambda xy: xy - t_fb, 500, 380)
    ref_valid = np.ones(ref.shape, bool)
    ref_valid[:, 300:] = False  # no content right of x = 300 (frame x ~ 270)
    ref[~ref_valid] = 0
    cfg = TemplateConfig(spacing_px=40, template_px=41, search_px=10, dither_iterations=1)
    cps = template_control_points(
        frame,
        ref,
        lambda xy: xy + t_ref + 1.5,  # the model is 1.5 px off; the search corrects it
        None,
        cfg,
        ref_valid=ref_valid,
        fallback=Reference(fb, lambda xy: xy + t_fb - 1.0),
    )
    from_ref, from_fb = cps.source == 0, cps.source == 1
    assert from_ref.sum() >= 20 and from_fb.sum() >= 20
    # Where the first reference has content it is used; the fallback only beyond it.
    assert (cps.src[from_ref, 0] + t_ref[0] + cfg.half_template + cfg.search_radius < 300 + 2).all()
    assert (cps.src[from_fb, 0] + t_ref[0] + cfg.half_template + cfg.search_radius > 300 - 2).all()
    np.testing.assert_allclose(
        cps.dst[from_ref] - cps.src[from_ref], np.tile(t_ref, (from_ref.sum(), 1)), atol=0.15
    )
    np.testing.assert_allclose(
        cps.dst[from_fb] - cps.src[from_fb], np.tile(t_fb, (from_fb.sum(), 1)), atol=0.15
    )
    # Without a fallback those templates are simply not matched.
    alone = template_control_points(
        frame, ref, lambda xy: xy + t_ref + 1.5, None, cfg, ref_valid=ref_valid
    )
    assert (alone.source == 0).all() and len(alone) == from_ref.sum()
    with pytest.raises(ValueError, match="fallback reference needs warp_reference=True"):
        template_control_points(
            frame,
            ref,
            lambda xy: xy + t_ref,
            None,
            TemplateConfig(warp_reference=False),
            fallback=Reference(fb, lambda xy: xy + t_fb),
        )


def test_min_templates_shrinks_the_spacing_for_small_frames():
    cfg = TemplateConfig(spacing_px=100, template_px=75, min_templates=200)
    big = template_grid(2560, 1920, cfg)
    assert len(big) == 25 * 19  # the spacing holds enough templates: unchanged
    small = template_grid(640, 480, cfg)
    assert len(small) >= 200 and len(template_grid(640, 480, TemplateConfig(spacing_px=100))) < 40
    step = np.diff(np.unique(small[:, 0]))
    assert (step == step[0]).all() and step[0] < 100


def test_sparse_grid_warps_only_its_windows_to_the_same_points(monkeypatch):
    """A sparse grid (an intra-sensor frame's) warps the reference over its search windows
    only; the control points are those of the whole-canvas warp, to the bit, also where the
    reference has no content."""
    from registration.matching import templates

    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)  # 960x540
    valid = np.ones(ref.shape, bool)
    valid[:, 700:] = False  # windows there are unusable
    frame_size = (560, 360)
    truth = bent_warp((ref.shape[1], ref.shape[0]), frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model((ref.shape[1], ref.shape[0]), frame_size)
    cfg = TemplateConfig(spacing_px=160, min_templates=0, edge_template_px=31)
    calls = []
    real = templates._Searches.ref_windows

    def spy(self, *args):
        calls.append(len(args[0]))
        return real(self, *args)

    monkeypatch.setattr(templates._Searches, "ref_windows", spy)
    sparse = template_control_points(frame, ref, coarse, coarse_inv, cfg, ref_valid=valid)
    assert calls and len(sparse) >= 8
    monkeypatch.setattr(templates._Searches, "windowed", lambda self, n, win: False)
    whole = template_control_points(frame, ref, coarse, coarse_inv, cfg, ref_valid=valid)
    assert len(sparse) == len(whole)
    for name in ("src", "dst", "score", "source"):
        np.testing.assert_array_equal(getattr(sparse, name), getattr(whole, name))
    # Dense grids (the reference frame's) warp the whole canvas once.
    calls.clear()
    template_control_points(frame, ref, coarse, coarse_inv, TemplateConfig(spacing_px=25))
    assert not calls


def _shadows(shape, shift, seed: int) -> np.ndarray:
    """Brightness factors (H, W) float32: 0.45 inside 40 random rectangles (the shadows of
    buildings), 1 elsewhere; the rectangles' far edges moved by ``shift`` (x, y) px, as a sun
    at another azimuth casts them."""
    rng = np.random.default_rng(seed)
    h, w = shape
    factor = np.ones((h, w), np.float32)
    for _ in range(40):
        x, y = rng.integers(0, w - 40), rng.integers(0, h - 40)
        bw, bh = rng.integers(12, 40, size=2)
        x1, y1 = x + bw + int(shift[0]), y + bh + int(shift[1])
        factor[y : max(y1, y + 1), x : max(x1, x + 1)] = 0.45
    return cv2.GaussianBlur(factor, (0, 0), 0.7)


@pytest.mark.parametrize("gain, offset", [(1.0, 0.0), (0.55, 60.0)])
def test_change_mask_removes_the_pull_of_moved_shadows(gain, offset):
    # The frame shows the reference shifted by a known fractional offset; both carry shadows,
    # the reference's 4 px longer in y (another sun). Unmasked, the moved shadow edges pull the
    # peaks towards +y; the change mask leaves the pixels whose brightness departs from the
    # template's photometric line out. The second case is a hazy map of another sensor (gain
    # 0.55, offset 60): a constant brightness ratio would call most of each template changed.
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25).astype(np.float32)
    shift = np.array([3.3, -2.6])
    frame = warp_into(ref, lambda xy: xy + shift + 100, 560, 340).astype(np.float32)
    frame_sun = _shadows(frame.shape, (0, 0), seed=5)
    # The same shadows in reference pixels, each 4 px longer in y there.
    ref_sun = np.ones_like(ref)
    ref_sun[100 : 100 + 340, 100 : 100 + 560] = warp_into(
        _shadows(frame.shape, (0, 4), seed=5), lambda xy: xy - shift, 560, 340
    )
    frame_u8 = np.clip(frame * frame_sun, 0, 255).astype(np.uint8)
    ref_u8 = np.clip(gain * ref * ref_sun + offset, 0, 255).astype(np.uint8)
    model = lambda xy: xy + 100.0  # noqa: E731
    bias, median = {}, {}
    for ratio in (0.0, CHANGE_LOG_RATIO):
        cfg = TemplateConfig(change_log_ratio=ratio)
        cp = template_control_points(frame_u8, ref_u8, model, None, cfg)
        err = cp.dst - (cp.src + shift + 100)
        bias[ratio], median[ratio] = np.mean(err[:, 1]), np.median(np.hypot(*err.T))
        assert len(cp) > 0.8 * len(template_grid(560, 340, cfg)), (ratio, len(cp))
    assert bias[0.0] > 0.1, bias  # the moved shadows do pull the unmasked peaks
    assert abs(bias[CHANGE_LOG_RATIO]) < 0.2 * bias[0.0], bias
    assert median[CHANGE_LOG_RATIO] < 0.6 * median[0.0], median


def test_change_mask_leaves_unchanged_scenes_alone():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)
    shift = np.array([3.3, -2.6])
    frame = warp_into(ref, lambda xy: xy + shift + 100, 560, 340)
    model = lambda xy: xy + 100.0  # noqa: E731
    med = []
    for ratio in (0.0, CHANGE_LOG_RATIO):
        cp = template_control_points(
            frame, ref, model, None, TemplateConfig(change_log_ratio=ratio)
        )
        med.append(np.median(np.linalg.norm(cp.dst - (cp.src + shift + 100), axis=1)))
    assert med[1] < 0.03 and med[1] < med[0] + 0.005, med


def test_masked_ncc_equals_opencvs_masked_correlation():
    from registration.matching.ncc_peaks import _masked_ncc

    rng = np.random.default_rng(3)
    window = (texture(81, 81, seed=4)).astype(np.uint8)
    tpl = window[3:78, 4:79].copy()
    keep = rng.random(tpl.shape) > 0.3
    ours = _masked_ncc(tpl, keep)(window)
    theirs = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED, mask=keep.astype(np.uint8))
    np.testing.assert_allclose(ours, theirs, atol=2e-4)
    assert np.unravel_index(np.argmax(ours), ours.shape) == (3, 4)
    # Flat over the kept pixels: no peak there.
    assert (_masked_ncc(tpl, keep)(np.full((81, 81), 7, np.uint8)) == -1).all()


def test_matches_in_a_strongly_corrected_frame_are_read_through_the_warps_lattice():
    """A raw frame taken through a γ = 0.6 Harris lens: it maps to the reference with a
    curvature that the warp's lattice (nodes 8 px apart) follows only to tenths of a px in the
    corners. A match found in the warped reference is where the warp put that content, so
    ``dst`` is read through the lattice. Against the exact truth: median 0.027 px inside, 0.119
    px in the corner ring (the model itself read at the match: 0.083 and 0.319 px)."""
    from registration.lens import Camera

    w, h = 320, 240
    camera = Camera(0.6, w, h)
    ref = texture(700, 560, seed=3)

    def ref_from_frame(q):  # raw frame px -> reference px: the lens, then a shift
        return camera.corrected_from_raw(np.asarray(q, np.float64)) + (190.0, 160.0)

    frame = warp_into(ref, ref_from_frame, w, h)  # exact at every pixel (step 1)
    cfg = TemplateConfig(warp_reference=True, edge_template_px=31)
    cp = template_control_points(frame, ref, ref_from_frame, None, cfg)
    err = np.linalg.norm(cp.dst - ref_from_frame(cp.src), axis=1)
    r = np.hypot(*(cp.src - [(w - 1) / 2, (h - 1) / 2]).T) / np.hypot(w / 2, h / 2)
    ring = r > 0.85
    assert ring.sum() >= 4 and (~ring).sum() >= 30, (ring.sum(), (~ring).sum())
    assert np.median(err[~ring]) < 0.05, np.median(err[~ring])  # measured 0.027
    assert np.median(err[ring]) < 0.2, err[ring].round(3)  # measured 0.119
