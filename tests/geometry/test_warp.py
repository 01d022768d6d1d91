"""registration.geometry.warp against independent implementations: scipy's ``map_coordinates`` for
bilinear and nearest sampling, Keys' cubic convolution written out here for bicubic, and
analytic images whose value at any point is known. The project's other tests build their warped
inputs with ``warp.remap`` itself, so a bug here would be shared by input and code under test;
these tests do not use it to make their expectations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from registration.geometry import warp

# OpenCV quantises sampling positions to 1/32 px for bilinear and bicubic sampling: the value
# error is at most |gradient| / 64 (plus float rounding).
POSITION_QUANTUM = 1.0 / 32


def smooth_image(h: int = 60, w: int = 80, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.uniform(0, 255, (h, w)), 2.0).astype(np.float32)


def random_map(h_out, w_out, lo, hi, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xs = rng.uniform(lo[0], hi[0], (h_out, w_out))
    ys = rng.uniform(lo[1], hi[1], (h_out, w_out))
    return np.stack([xs, ys], axis=-1).astype(np.float32)


def max_gradient(img: np.ndarray) -> float:
    gy, gx = np.gradient(img.astype(np.float64))
    return float(np.hypot(gx, gy).max())


def test_pixel_grid_holds_each_pixels_own_coordinates():
    grid = warp.pixel_grid(5, 3)
    ys, xs = np.mgrid[0:3, 0:5]
    assert grid.shape == (3, 5, 2) and grid.dtype == np.float32
    np.testing.assert_array_equal(grid[..., 0], xs)
    np.testing.assert_array_equal(grid[..., 1], ys)
    img = smooth_image()
    np.testing.assert_array_equal(warp.remap(img, warp.pixel_grid(80, 60)), img)


def test_bilinear_remap_matches_scipy_map_coordinates():
    img = smooth_image()
    smap = random_map(40, 50, (0, 0), (79, 59))
    got = warp.remap(img, smap, interpolation="linear")
    # scipy: coordinates (row, col) = (y, x); pixel centres at integers, as in conventions.md.
    expected = ndimage.map_coordinates(img, [smap[..., 1], smap[..., 0]], order=1)
    tol = max_gradient(img) * POSITION_QUANTUM / 2 + 1e-3
    assert np.abs(got - expected).max() < tol
    # Colour images: each channel alike.
    rgb = np.stack([img, 255 - img, img / 2], axis=-1)
    got3 = warp.remap(rgb, smap)
    for c in range(3):
        exp = ndimage.map_coordinates(rgb[..., c], [smap[..., 1], smap[..., 0]], order=1)
        assert np.abs(got3[..., c] - exp).max() < tol


def test_nearest_remap_matches_scipy():
    img = smooth_image()
    smap = random_map(40, 50, (0, 0), (79, 59), seed=2)
    # Away from the half-pixel ties, where the two may round differently.
    frac = np.abs(smap - np.floor(smap) - 0.5)
    ok = (frac > 0.05).all(axis=-1)
    got = warp.remap(img, smap, interpolation="nearest")
    expected = ndimage.map_coordinates(img, [smap[..., 1], smap[..., 0]], order=0)
    np.testing.assert_array_equal(got[ok], expected[ok])


def _keys_cubic(img: np.ndarray, x: np.ndarray, y: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Keys' cubic convolution (OpenCV's INTER_CUBIC uses a = -0.75), written out."""

    def kernel(t):
        t = np.abs(t)
        return np.where(
            t <= 1,
            (a + 2) * t**3 - (a + 3) * t**2 + 1,
            np.where(t < 2, a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a, 0.0),
        )

    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    out = np.zeros(x.shape)
    for j in range(-1, 3):
        for i in range(-1, 3):
            w = kernel(x - (x0 + i)) * kernel(y - (y0 + j))
            out += w * img[y0 + j, x0 + i]
    return out


def test_bicubic_remap_matches_keys_cubic_convolution():
    img = smooth_image()
    smap = random_map(30, 40, (2, 2), (76, 56), seed=3)  # the 4x4 support stays inside
    got = warp.remap(img, smap, interpolation="cubic")
    expected = _keys_cubic(
        img.astype(np.float64), smap[..., 0].astype(float), smap[..., 1].astype(float)
    )
    # OpenCV rounds x and y to its position quantum independently, so the position is off by up to
    # half a quantum in each: sqrt(2)/2 of a quantum along the gradient (measured 0.262 with
    # OpenCV 4.14 against a bound of 0.33; 5.0 is closer).
    bound = max_gradient(img) * POSITION_QUANTUM * np.sqrt(2) / 2 + 1e-2
    assert np.abs(got - expected).max() < bound


def test_outside_and_nan_get_the_border_value():
    img = smooth_image() + 10
    smap = np.array(
        [[[-5.0, 10.0], [np.nan, 3.0], [100.0, 20.0], [10.0, 1e9], [4.0, np.nan], [np.inf, 5.0],
          [6.0, -np.inf], [np.nan, np.nan], [np.nan, -np.inf]]], np.float32,
    )  # fmt: skip
    got = warp.remap(img, smap, border_value=-7)
    np.testing.assert_array_equal(got, [[-7] * 9])
    # The map given is not changed.
    assert np.isnan(smap[0, 1, 0]) and np.isinf(smap[0, 5, 0])
    # Half a pixel beyond the outer pixel centre: half image, half border (constant extension).
    edge = warp.remap(img, np.array([[[-0.5, 10.0]]], np.float32), border_value=0)
    assert edge[0, 0] == pytest.approx(img[10, 0] / 2, abs=0.05 * float(img[10, 0]))
    rgb = np.dstack([img, img, img]).astype(np.uint8)
    out = warp.remap(rgb, smap, border_value=(1, 2, 3))
    assert out.dtype == np.uint8 and (out[0, 0] == [1, 2, 3]).all()
    with pytest.raises(ValueError, match="interpolation"):
        warp.remap(img, smap, interpolation="lanczos")
    with pytest.raises(ValueError, match="source_map"):
        warp.remap(img, smap[..., 0])


def test_source_map_from_function_samples_pixel_centres_and_its_lattice_is_exact_for_affine():
    def affine(xy):
        return xy @ np.array([[1.1, 0.2], [-0.15, 0.9]]).T + [3.25, -7.5]

    h, w = 45, 67
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    direct = affine(np.c_[xs.ravel() + 4.0, ys.ravel() - 2.0]).reshape(h, w, 2)
    for step in (1, 4, 8):
        smap = warp.source_map_from_function(affine, w, h, step=step, origin=(4.0, -2.0))
        assert smap.shape == (h, w, 2) and smap.dtype == np.float32
        np.testing.assert_allclose(smap, direct, atol=2e-3, err_msg=f"step {step}")


def test_source_map_lattice_follows_a_curved_warp_closely():
    def curved(xy):
        x, y = xy[:, 0], xy[:, 1]
        return np.c_[x + 1e-4 * (x - 40) ** 2, y + 5e-5 * x * y]

    h, w = 70, 90
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    direct = curved(np.c_[xs.ravel(), ys.ravel()]).reshape(h, w, 2)
    smap = warp.source_map_from_function(curved, w, h, step=8)
    # Bilinear interpolation of a quadratic over 8 px cells: at most curvature * 8^2 / 8.
    assert np.abs(smap - direct).max() < 0.01


def test_warp_image_of_an_analytic_pattern():
    """A pattern known at every point, rendered through a known rotation and scale: each output
    pixel shows the pattern at the mapped position, and the mask marks exactly the pixels whose
    source lies within the image (beyond the outer pixels' edges is outside)."""
    h, w = 120, 160

    def pattern(x, y):
        return 100 + 60 * np.sin(x / 7.0) * np.cos(y / 9.0)

    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    img = pattern(xs, ys).astype(np.float32)
    a = np.radians(20.0)
    rot = 0.8 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    def src_from_out(xy):
        return xy @ rot.T + [30.0, -10.0]

    out, valid = warp.warp_image(img, src_from_out, 150, 130, step=8)
    oy, ox = np.mgrid[0:130, 0:150].astype(np.float64)
    src = src_from_out(np.c_[ox.ravel(), oy.ravel()]).reshape(130, 150, 2)
    inside = (src[..., 0] >= -0.5) & (src[..., 0] <= w - 0.5)
    inside &= (src[..., 1] >= -0.5) & (src[..., 1] <= h - 0.5)
    np.testing.assert_array_equal(valid, inside)
    interior = (
        (src[..., 0] >= 1) & (src[..., 0] <= w - 2) & (src[..., 1] >= 1) & (src[..., 1] <= h - 2)
    )
    assert interior.sum() > 5000
    truth = pattern(src[..., 0], src[..., 1])
    # Bilinear sampling of the pattern: its curvature over one pixel, under 0.7 here.
    assert np.abs(out - truth)[interior].max() < 0.7
    assert np.abs(out - truth)[interior].mean() < 0.25


@pytest.mark.parametrize("interpolation", ["nearest", "linear", "cubic"])
def test_prepared_map_gives_the_same_image(interpolation):
    img = (smooth_image() * 0.9).astype(np.uint8)
    smap = random_map(40, 50, (-3, -3), (82, 62), seed=4)
    smap[0, :5] = np.nan
    prepared = warp.prepare_source_map(smap, interpolation=interpolation)
    assert prepared.shape == (40, 50)
    a = warp.remap(img, smap, interpolation=interpolation, border_value=9)
    b = warp.remap_prepared(img, prepared, border_value=9)
    # Fixed point: positions quantised to 1/32 px by both (differently rounded), plus one grey
    # level of rounding.
    # level of rounding (where a sample blends with the border the jump is the gradient).
    inside = (smap >= 0).all(axis=-1) & (smap[..., 0] <= 79) & (smap[..., 1] <= 59)
    tol = max_gradient(img) * POSITION_QUANTUM + 1
    assert np.abs(a.astype(int) - b.astype(int))[inside].max() <= tol
    assert (b[0, :5] == 9).all()


def test_a_mapping_that_jumps_between_nodes_renders_no_ghost():
    """Far from a frame, a model's inverse can jump between two lattice nodes from beyond the
    image's left edge to beyond its right edge (a second branch of a polyprojective's inverse,
    a projective's horizon). Interpolating the lattice there passes through the image and would
    render a ghost of it; no output pixel truly maps inside, so none may be valid."""
    from registration.render import render_registered

    img = np.full((60, 80), 200, np.uint8)

    def jump(xy):
        x = np.where(xy[:, 0] < 101.3, -100.0, 180.0)
        return np.c_[x, xy[:, 1] * 0.5]

    # The case is real: the interpolated lattice alone puts pixels inside the image.
    lattice = warp.source_map_from_function(jump, 200, 100, step=8)
    assert ((lattice[..., 0] >= -0.5) & (lattice[..., 0] <= 79.5)).sum() >= 100
    for step in (4, 8):
        out, valid = warp.warp_image(img, jump, 200, 100, step=step)
        assert not valid.any() and not out.any(), step
    out, mask = render_registered(img, jump, (200, 100), step=8, return_mask=True)
    assert not mask.any() and not out.any()


def test_ghost_check_evaluates_a_smooth_mappings_straddling_pixels_exactly():
    """Where a smooth mapping's frame pokes into a lattice cell whose four nodes lie outside it
    (the corners of a raw frame seen through a γ = 0.7 Harris correction), the check evaluates
    those pixels exactly: they equal the exact mapping and differ from the interpolated lattice
    by a fraction of a px, and they are the only pixels it changes (2 here)."""
    from registration.lens import Camera

    camera = Camera(0.7, 160, 120)

    def raw_from_output(xy):  # output = corrected frame px, shifted so the frame is inside
        return camera.raw_from_corrected(np.asarray(xy, np.float64) + [-60.0, -50.0])

    plain = warp.source_map_from_function(raw_from_output, 280, 220, step=8)
    checked = warp.source_map_from_function(
        raw_from_output, 280, 220, step=8, source_size=(160, 120)
    )
    exact = warp.source_map_from_function(raw_from_output, 280, 220, step=1)
    changed = (plain != checked).any(axis=2)
    # Measured: 2 px, where the frame's corners poke into such cells.
    assert 1 <= changed.sum() <= 10, changed.sum()
    np.testing.assert_array_equal(checked[changed], exact[changed])
    assert np.abs(plain - checked)[changed].max() < 0.1  # measured 0.024


def test_an_unclipped_mappings_edge_is_evaluated_exactly():
    """A mapping not clipped at the frame's edge (its nodes just beyond it carry on) is
    interpolated across the edge like anywhere else; with ``exact_edge_px`` the pixels whose
    interpolated source lies that close to the edge are evaluated exactly, so the frame's
    extent (the mask every caller draws from the source) is the exact one. A γ = 0.7 frame's
    corrected edge curves between the lattice's nodes: interpolated alone, the extent is off by
    a few pixels at its corners."""
    from registration.lens import Camera

    camera = Camera(0.7, 160, 120)

    def raw_from_output(xy):
        return camera.raw_from_corrected(np.asarray(xy, np.float64) + [-60.0, -50.0])

    def inside(smap):
        sx, sy = smap[..., 0], smap[..., 1]
        return (sx >= -0.5) & (sx <= 159.5) & (sy >= -0.5) & (sy <= 119.5)

    exact = warp.source_map_from_function(raw_from_output, 280, 220, step=1)
    kwargs = dict(step=8, source_size=(160, 120))
    plain = warp.source_map_from_function(raw_from_output, 280, 220, **kwargs)
    edged = warp.source_map_from_function(raw_from_output, 280, 220, exact_edge_px=0.5, **kwargs)
    assert (inside(plain) != inside(exact)).sum() >= 3  # the case is real
    np.testing.assert_array_equal(inside(edged), inside(exact))
    # Only pixels near the edge are evaluated exactly: the rest is the lattice's, to the bit.
    changed = (edged != plain).any(axis=2)
    assert 0 < changed.sum() < 0.1 * inside(exact).sum()
    np.testing.assert_array_equal(edged[changed], exact[changed])
    sx, sy = exact[..., 0], exact[..., 1]
    to_edge = np.minimum.reduce(
        [np.abs(sx + 0.5), np.abs(sx - 159.5), np.abs(sy + 0.5), np.abs(sy - 119.5)]
    )
    assert to_edge[changed].max() < 0.5 + 0.1
