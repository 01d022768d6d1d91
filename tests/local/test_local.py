"""Local displacement field (paper section 5): known fields recovered, moving cars rejected."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from registration import local
from registration.geometry import DisplacementField, displacement_field, warp
from registration.local import NEIGHBOUR_OUTLIER, NO_CONSENSUS, OK, RIVAL_MOTION, LocalConfig
from registration.matching import dense_flow
from tests.conftest import shared_data

W, H = 640, 480


def texture(width: int, height: int, seed: int, scales=((2, 1.0), (4, 1.0), (8, 1.0), (16, 1.0))):
    """Aerial-like multi-scale random texture, float32 zero mean unit variance."""
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width), np.float32)
    for s, a in scales:
        n = rng.standard_normal((height // s + 2, width // s + 2)).astype(np.float32)
        img += (
            a
            * cv2.resize(n, (width + 2 * s, height + 2 * s), interpolation=cv2.INTER_CUBIC)[
                :height, :width
            ]
        )
    return (img - img.mean()) / img.std()


def to_u8(img):
    return np.clip(img, 0, 255).astype(np.uint8)


def smooth_field(xy):
    """A few px, spatially varying (the residual a global model leaves): (N,2) -> (N,2)."""
    x, y = xy[:, 0], xy[:, 1]
    return np.stack(
        [
            1.5 + 1.2 * np.sin(2 * np.pi * x / 2000 + 0.3) + 0.4 * (y / H),
            -1.0 + 1.0 * np.cos(2 * np.pi * y / 1600) + 0.5 * (x / W),
        ],
        axis=1,
    )


def warp_by(reference, e):
    """registered(y) = reference(y - e(y)): content of reference at x appears at x + d(x) with
    d(x) = e(x + d(x)). Returns (registered, true d as a function)."""
    h, w = reference.shape
    grid = warp.pixel_grid(w, h).reshape(-1, 2).astype(np.float64)
    registered = warp.remap(reference, (grid - e(grid)).reshape(h, w, 2), interpolation="cubic")

    def d_true(xy):
        d = e(xy)
        for _ in range(60):
            d = e(xy + d)
        return d

    return registered, d_true


# --------------------------------------------------------------------------------------------
# Field layout and mappings


def test_grid_nodes_sit_on_the_base_lattice_and_cover_the_crop():
    (x0, y0), (gx, gy) = displacement_field.grid_nodes(1280, 960, 200, origin=(100, 50))
    assert (x0, y0) == (0.0, 0.0)
    assert (gx, gy) == (8, 7)  # nodes 0..1400 bracket x 100..1379, 0..1200 bracket y 50..1009
    f = DisplacementField.zeros(1280, 960, 200, origin=(100, 50))
    ext = f.extent
    assert ext[0] <= 100 - 0.5 and ext[2] >= 100 + 1279.5
    assert ext[1] <= 50 - 0.5 and ext[3] >= 50 + 959.5
    # A crop shifted by a pixel keeps its nodes.
    assert displacement_field.grid_nodes(1280, 960, 200, origin=(101, 49))[0] == (0.0, 0.0)
    assert displacement_field.grid_nodes(400, 400, 200, origin=(200, 200)) == (
        (200.0, 200.0),
        (3, 3),
    )


def test_sample_and_dense_agree_bilinear_and_nan_outside(rng):
    vec = rng.normal(size=(3, 4, 2)).astype(np.float32)
    f = DisplacementField((10.0, 20.0), 100.0, vec, np.ones((3, 4), bool))
    # Exact at nodes, bilinear midway.
    assert np.allclose(f.sample([[10, 20], [310, 220]]), [vec[0, 0], vec[2, 3]], atol=1e-6)
    mid = f.sample([[60, 70]])[0]
    assert np.allclose(mid, vec[:2, :2].reshape(-1, 2).mean(axis=0), atol=1e-6)
    # Constant beyond the outer nodes, NaN outside the cells.
    assert np.allclose(f.sample([[-39, 20]]), vec[0, 0], atol=1e-6)
    assert np.isnan(f.sample([[-41, 20]])).all()
    dense = f.dense(400, 300, origin=(-50, -40))
    ys, xs = np.mgrid[0:300:7, 0:400:9]
    pts = np.c_[xs.ravel() - 50.0, ys.ravel() - 40.0]
    s = f.sample(pts)
    d = dense[ys.ravel(), xs.ravel()]
    assert np.array_equal(np.isnan(s), np.isnan(d))
    ok = np.isfinite(s)
    assert np.allclose(s[ok], d[ok], atol=1e-5)
    # Round trip through plain arrays (what result folders store).
    g = DisplacementField.from_arrays({f"field_{k}": v for k, v in f.to_arrays().items()}, "field_")
    assert g.origin == f.origin and g.spacing == f.spacing
    assert np.array_equal(g.vectors, f.vectors) and np.array_equal(g.valid, f.valid)


def test_local_frame_to_base_inverts_local_base_to_frame(rng):
    vec = rng.uniform(-3, 3, size=(4, 5, 2)).astype(np.float32)
    f = DisplacementField((0.0, 0.0), 200.0, vec, np.ones((4, 5), bool))
    a = np.array([[1.01, 0.02], [-0.03, 0.99]])
    t = np.array([5.0, -7.0])

    def frame_to_base(q):
        return q @ a.T + t

    def base_to_frame(b):
        return (b - t) @ np.linalg.inv(a).T

    q = rng.uniform(0, 700, size=(200, 2))
    x = displacement_field.local_frame_to_base(frame_to_base, f, q)
    assert np.isfinite(x).all()
    # x + d(x) = g(q) to the 1e-4 px the iteration promises.
    assert np.abs(x + f.sample(x) - frame_to_base(q)).max() < 1e-4
    back = displacement_field.local_base_to_frame(base_to_frame, f, x)
    assert np.abs(back - q).max() < 1e-3
    # Beyond the field it is extended constantly (the global mapping decides coverage) ...
    far = displacement_field.local_frame_to_base(frame_to_base, f, [[5000.0, 5000.0]])
    assert np.allclose(far, frame_to_base(np.array([[5000.0, 5000.0]])) - vec[-1, -1], atol=1e-4)
    assert np.allclose(f.sample([[9000.0, 9000.0]], outside="clamp"), vec[-1, -1], atol=1e-6)
    # ... and NaN from the global mapping stays NaN, never an exception.
    nan_map = displacement_field.local_frame_to_base(
        lambda q: np.full_like(q, np.nan), f, [[1.0, 2.0]]
    )
    assert np.isnan(nan_map).all()
    assert np.isnan(
        displacement_field.local_base_to_frame(lambda b: np.full_like(b, np.nan), f, [[1.0, 2.0]])
    ).all()


def test_apply_field_direction_constant_shift():
    ref = to_u8(128 + 40 * texture(W, H, 1))
    # Content of the reference at x sits at x + (3, -2) in the registered image.
    registered = warp.remap(ref, warp.pixel_grid(W, H) - np.float32([3, -2]), interpolation="cubic")
    f = DisplacementField(
        (0.0, 0.0), 200.0, np.tile(np.float32([3, -2]), (3, 4, 1)), np.ones((3, 4), bool)
    )
    out = displacement_field.apply_field(registered, f, interpolation="cubic")
    inner = (slice(10, H - 10), slice(10, W - 10))
    assert np.abs(out[inner].astype(int) - ref[inner]).mean() < 1.0


def test_fill_invalid_uses_neighbours():
    vec = np.zeros((3, 3, 2), np.float32)
    valid = np.zeros((3, 3), bool)
    vec[0, 0] = (2, 0)
    valid[0, 0] = True
    vec[2, 2] = (0, 4)
    valid[2, 2] = True
    out = local.fill_invalid(vec, valid)
    assert np.allclose(out[0, 0], (2, 0)) and np.allclose(out[2, 2], (0, 4))
    assert np.allclose(out[0, 1], (2, 0))  # only (0,0) is a neighbour
    assert np.allclose(out[1, 1], (1, 2))  # both are
    assert np.allclose(local.fill_invalid(vec, np.zeros((3, 3), bool)), 0)


# --------------------------------------------------------------------------------------------
# Consensus


def test_reqcon_drops_injected_outliers_exactly(rng):
    disp = np.array([1.0, -0.5]) + rng.normal(0, 0.1, size=(40, 2))
    # REQCON drops ceil(5 % of 40) = 2 per round: four outliers go in exactly two rounds.
    outliers = [3, 17, 29, 35]
    disp[outliers] += [[6.0, 0.0], [0.0, -7.0], [4.0, 4.0], [-5.0, 2.0]]
    pos = rng.uniform(0, 200, size=(40, 2))
    c = local.cell_consensus(pos, disp, (100, 100), LocalConfig())
    assert c.status == OK
    assert np.array_equal(np.nonzero(~c.kept)[0], outliers)
    assert np.allclose(c.vector, [1.0, -0.5], atol=0.05)


def test_rival_motion_rejects_two_coherent_motions(rng):
    static = np.array([1.0, 0.0]) + rng.normal(0, 0.1, size=(60, 2))
    cars = np.array([1.0, 8.0]) + rng.normal(0, 0.1, size=(40, 2))
    disp = np.r_[static, cars]
    pos = rng.uniform(0, 200, size=(100, 2))
    c = local.cell_consensus(pos, disp, (100, 100), LocalConfig())
    assert c.status == RIVAL_MOTION and np.isnan(c.vector).all()
    # REQCON itself found the majority: the guard rejects, it does not pick.
    assert c.kept[:60].all() and not c.kept[60:].any()
    # Without the guard the same matches give the static vector (the majority).
    c2 = local.cell_consensus(pos, disp, (100, 100), LocalConfig(rival_ratio=0))
    assert c2.status == OK and np.allclose(c2.vector, [1.0, 0.0], atol=0.05)
    # A small car group (15 % of the matches) is no rival.
    c3 = local.cell_consensus(pos[:70], np.r_[static, cars[:10]], (100, 100), LocalConfig())
    assert c3.status == OK and np.allclose(c3.vector, [1.0, 0.0], atol=0.05)


def test_no_consensus_from_random_matches(rng):
    disp = rng.uniform(-10, 10, size=(30, 2))
    c = local.cell_consensus(rng.uniform(0, 200, (30, 2)), disp, (100, 100), LocalConfig())
    assert c.status == NO_CONSENSUS


def test_neighbour_check_flags_the_odd_cell():
    vec = np.tile(np.float32([1.0, -1.0]), (4, 5, 1))
    vec[1, 2] = (1.0, 7.0)
    vec[3, 0] = (1.5, -1.4)  # a small, genuine variation
    valid = np.ones((4, 5), bool)
    bad = local.neighbour_check(vec, valid, 3.0, 3)
    assert np.argwhere(bad).tolist() == [[1, 2]]


# --------------------------------------------------------------------------------------------
# End to end on images


def test_estimate_field_recovers_a_known_smooth_field():
    ref = to_u8(128 + 40 * texture(W, H, 7))
    registered, d_true = warp_by(ref, smooth_field)
    f, stats = local.estimate_field(registered, ref, LocalConfig())
    # Nodes on the 200 px lattice bracket the 640x480 image: x 0..800, y 0..600.
    assert f.shape == (4, 5) and f.origin == (0.0, 0.0)
    # The cells of the last row and column lie wholly outside the image: no matches, filled.
    expected = np.zeros((4, 5), bool)
    expected[:3, :4] = True
    assert np.array_equal(f.valid, expected), stats.counts()
    nodes = f.node_xy.reshape(-1, 2)
    err = np.linalg.norm(f.vectors.reshape(-1, 2) - d_true(nodes), axis=1)
    assert err[f.valid.ravel()].max() < 0.3, err
    # The dense field: applying it leaves well under 1 px, far less than without it.
    grid = warp.pixel_grid(W, H).reshape(-1, 2).astype(np.float64)
    truth = d_true(grid)
    after = np.linalg.norm(f.dense(W, H).reshape(-1, 2) - truth, axis=1)
    before = np.linalg.norm(truth, axis=1)
    assert np.nanmean(after) < 1.0 and np.nanmean(after) < 0.25 * before.mean()
    # And the locally registered image matches the reference better than the global one.
    out = displacement_field.apply_field(registered, f, interpolation="cubic")
    inner = (slice(12, H - 12), slice(12, W - 12))
    diff_after = np.abs(out[inner].astype(float) - ref[inner]).mean()
    diff_before = np.abs(registered[inner].astype(float) - ref[inner]).mean()
    assert diff_after < 0.5 * diff_before


def test_estimate_field_on_real_aerial_imagery():
    path = shared_data("songdo-vision-drone", "images", "00003.jpg")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    ref = np.ascontiguousarray(img[800 : 800 + H, 1500 : 1500 + W])
    registered, d_true = warp_by(ref, smooth_field)
    f, stats = local.estimate_field(registered, ref, LocalConfig())
    ok = f.valid.ravel()
    assert ok.sum() >= 8, stats.counts()
    err = np.linalg.norm(f.vectors.reshape(-1, 2) - d_true(f.node_xy.reshape(-1, 2)), axis=1)
    assert err[ok].max() < 0.3, err


def test_valid_mask_marks_cells_outside():
    ref = to_u8(128 + 40 * texture(W, H, 3))
    registered, _ = warp_by(ref, smooth_field)
    mask = np.ones((H, W), bool)
    mask[:, 420:] = False  # the frame's footprint ends here
    registered[~mask] = 0
    f, stats = local.estimate_field(registered, ref, LocalConfig(), valid_mask=mask)
    # Lattice columns x = 0, 200, 400, 600, 800: the cell of x = 400 (300..500) is 60 % inside
    # the footprint, those of 600 and 800 not at all; row y = 600 is outside the image.
    assert (stats.cell_status[:, 3:] == local.OUTSIDE).all()
    assert (stats.cell_status[3] == local.OUTSIDE).all()
    assert (stats.cell_status[:3, :3] == OK).all()
    assert not f.valid[:, 3:].any()
    assert np.isfinite(f.vectors).all()


CAR = np.full((26, 12), 230, np.float32)
CAR[4:9, 2:10] = 40
CAR[17:22, 2:10] = 60
CAR[11:14, 3:9] = 120


def _paste(img, x, y):
    h, w = CAR.shape
    ys, xs = np.mgrid[0 : img.shape[0], 0 : img.shape[1]].astype(np.float32)
    sx, sy = xs - x, ys - y
    inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
    img[inside] = cv2.remap(CAR, sx, sy, cv2.INTER_LINEAR)[inside]


def car_scene(flat_cell: bool):
    """Reference and registered image with a static shift STATIC, and three lanes of identical
    cars through cell (1, 1) that move 8 px down between the two images."""
    pad = 20
    bg = texture(W + 2 * pad, H + 2 * pad, 5)
    base = 128 + 40 * bg
    (x0, y0), _ = displacement_field.grid_nodes(W, H, 200)
    cx, cy = x0 + 200 + pad, y0 + 200 + pad
    if flat_cell:  # little ground texture in that cell: the cars dominate its matches
        m = np.zeros_like(base)
        m[int(cy) - 100 : int(cy) + 100, int(cx) - 100 : int(cx) + 100] = 1
        m = cv2.GaussianBlur(m, (0, 0), 8)
        base = base * (1 - m) + (128 + 6 * bg) * m
    ref_big, reg_big = base.copy(), base.copy()
    for lane in (-40, 0, 40):
        for k in range(7):
            x, y = cx + lane - 6, cy - 100 + 30 * k
            _paste(ref_big, x, y)
            _paste(reg_big, x, y + 8.0)
    ref = to_u8(ref_big[pad : pad + H, pad : pad + W])
    grid = warp.pixel_grid(W, H)
    src = grid - np.float32(STATIC) + pad
    registered = warp.remap(to_u8(reg_big), src, interpolation="cubic")
    return ref, registered


STATIC = (1.2, -0.6)


def test_moving_cars_do_not_drag_the_cell():
    ref, registered = car_scene(flat_cell=False)
    f, stats = local.estimate_field(registered, ref, LocalConfig())
    assert stats.cell_status[1, 1] == OK
    assert np.linalg.norm(f.vectors[1, 1] - STATIC) < 0.5
    assert np.abs(f.vectors - STATIC).max() < 0.5


def test_guard_rejects_a_cell_dominated_by_cars():
    ref, registered = car_scene(flat_cell=True)
    # Without the guard the cars win the cell's consensus: dragged by ~8 px.
    unguarded = LocalConfig(rival_ratio=0, neighbour_tolerance_px=None)
    f0, s0 = local.estimate_field(registered, ref, unguarded)
    assert s0.cell_status[1, 1] == OK
    assert np.linalg.norm(f0.vectors[1, 1] - STATIC) > 5.0
    # With it the cell is rejected and filled from its neighbours.
    f, stats = local.estimate_field(registered, ref, LocalConfig())
    assert stats.cell_status[1, 1] in (NEIGHBOUR_OUTLIER, RIVAL_MOTION)
    assert not f.valid[1, 1]
    assert np.linalg.norm(f.vectors[1, 1] - STATIC) < 0.5


@pytest.mark.parametrize("model", ["translation", "affine"])
def test_cell_models_agree_on_a_constant_shift(model):
    ref = to_u8(128 + 40 * texture(W, H, 11))
    registered = warp.remap(
        ref, warp.pixel_grid(W, H) - np.float32([0.7, 1.9]), interpolation="cubic"
    )
    f, stats = local.estimate_field(registered, ref, LocalConfig(cell_model=model))
    assert stats.n_valid == 12
    assert np.abs(f.vectors - [0.7, 1.9]).max() < 0.15  # filled cells too


# --------------------------------------------------------------------------------------------
# The "flow" method (the default preset): same consensus and guard, dense DIS samples


FLOW = replace(LocalConfig(), **local.FLOW_OVERRIDES)


def test_flow_method_recovers_a_known_smooth_field():
    ref = to_u8(128 + 40 * texture(W, H, 7))
    registered, d_true = warp_by(ref, smooth_field)
    f, stats = local.estimate_field(registered, ref, FLOW)
    assert f.spacing == 100 and f.shape == (6, 8)  # x 0..700, y 0..500
    assert stats.n_valid == f.valid.size, stats.counts()
    nodes = f.node_xy.reshape(-1, 2)
    err = np.linalg.norm(f.vectors.reshape(-1, 2) - d_true(nodes), axis=1)
    # Nodes inside the image (the affine cell model keeps them unbiased even where the samples
    # lie to one side, as in the cells cut by the image border); the nodes beyond it are
    # extrapolations from a sliver of samples.
    inside = (nodes[:, 0] <= W - 1) & (nodes[:, 1] <= H - 1)
    assert err[inside].max() < 0.2, err
    assert err.max() < 0.5, err
    grid = warp.pixel_grid(W, H).reshape(-1, 2).astype(np.float64)
    after = np.linalg.norm(f.dense(W, H).reshape(-1, 2) - d_true(grid), axis=1)
    assert np.nanmean(after) < 0.2


@pytest.mark.parametrize("flat_cell", [False, True])
def test_flow_method_is_not_dragged_by_cars(flat_cell):
    ref, registered = car_scene(flat_cell)
    cfg = replace(FLOW, spacing_px=200)  # the car scene's cell (1, 1) is laid out for 200 px
    f, stats = local.estimate_field(registered, ref, cfg)
    assert np.linalg.norm(f.vectors[1, 1] - STATIC) < 0.5
    assert np.abs(f.vectors - STATIC).max() < 0.5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cell_px": 0}, "cell_px and spacing_px must be positive"),
        ({"ratio": 1.5}, "ratio must be in"),
        ({"method": "orb"}, "method must be 'sift' or 'flow', got 'orb'"),
        ({"flow_preset": "slow"}, "flow_preset must be ultrafast, fast or medium, got 'slow'"),
        ({"flow_refinement_iterations": -1}, "flow_refinement_iterations must be None or >= 0"),
        ({"flow_patch_stride": 0}, "flow_patch_stride must be None or >= 1, got 0"),
        ({"cell_model": "quadratic"}, "cell_model must be"),
        ({"fit": "tps"}, "fit must be 'cells' or 'spline', got 'tps'"),
        ({"spline_smoothness": 0.0}, "spline_smoothness must be positive, got 0.0"),
    ],
)
def test_bad_config_names_the_value(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LocalConfig(**kwargs)


def test_field_stats_summary_is_json_ready():
    import json

    ref = to_u8(128 + 40 * texture(W, H, 2))
    registered, _ = warp_by(ref, smooth_field)
    _, stats = local.estimate_field(registered, ref, FLOW)
    d = json.loads(json.dumps(stats.to_dict()))
    assert d["n_valid"] == stats.n_valid and d["cells"]["ok"] == stats.n_valid
    assert d["time_total_s"] > 0 and d["matches_per_valid_cell"] > 100


def frame_of_base(base, base_from_frame, d, width, height):
    """A frame whose pixel q shows the base at B(q), where B + d(B) = base_from_frame(q) (the
    field convention of registration.local), found by fixed-point iteration."""
    q = warp.pixel_grid(width, height).reshape(-1, 2).astype(np.float64)
    g = base_from_frame(q)
    b = g.copy()
    for _ in range(30):
        b = g - d(b)
    smap = b.reshape(height, width, 2).astype(np.float32)
    return warp.remap(base, smap, interpolation="cubic")


def similarity(angle_deg, scale, offset):
    c, s = np.cos(np.radians(angle_deg)) * scale, np.sin(np.radians(angle_deg)) * scale

    def apply(q):
        return np.c_[c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]] + offset

    return apply


@pytest.mark.parametrize(("scale", "refinement"), [(1.0, None), (0.5, None), (0.5, 0)])
def test_field_measured_in_frame_geometry_recovers_a_known_field(scale, refinement):
    """The flow between the frame and the mid base image warped into it gives the field in base
    px exactly through the global mapping, at full and at half scale, and without DIS's
    variational refinement."""
    base = to_u8(128 + 40 * texture(1000, 900, 11))
    valid = np.ones(base.shape, bool)
    valid[:, 900:] = False  # the mid base image ends inside the frame's footprint
    g = similarity(6.0, 1.1, np.array([120.0, 60.0]))
    frame = frame_of_base(base, g, smooth_field, W, H)
    cfg = replace(
        FLOW, flow_scale=scale, flow_preset="medium", flow_refinement_iterations=refinement
    )
    reference = dense_flow.prepare_flow_reference(
        np.where(valid, base, 0).astype(np.uint8), valid, scale
    )
    f, stats = local.estimate_field_in_frame(frame, g, reference, cfg)
    nodes = f.node_xy.reshape(-1, 2)
    measured = f.valid.ravel()
    assert measured.sum() >= 20, stats.counts()
    # No node is measured where the mid base image has no content.
    assert (nodes[measured, 0] < 900 + cfg.cell_px / 2).all()
    err = np.linalg.norm(f.vectors.reshape(-1, 2)[measured] - smooth_field(nodes[measured]), axis=1)
    assert np.median(err) < (0.1 if scale == 1 else 0.15), err
    assert err.max() < 0.5, err
    # Frame points through the global mapping and the field land on their true base points.
    q = np.array([[100.0, 100.0], [320.0, 240.0], [500.0, 380.0]])
    b_true = g(q)
    for _ in range(30):
        b_true = g(q) - smooth_field(b_true)
    b = displacement_field.local_frame_to_base(g, f, q)
    assert np.linalg.norm(b - b_true, axis=1).max() < 0.3


def test_one_flow_through_the_coarse_model_serves_both_stages():
    """The default preset measures a frame's flow once, through its coarse model (a few px off),
    draws the global model's control points from it and lets the local stage reuse it through
    the fine model: the points are true correspondences, and the field is the known one, as
    when the flow is measured through the fine model itself."""
    base = to_u8(128 + 40 * texture(1000, 900, 11))
    valid = np.ones(base.shape, bool)
    g = similarity(6.0, 1.1, np.array([120.0, 60.0]))
    coarse = similarity(6.15, 1.101, np.array([122.5, 58.0]))
    off = np.linalg.norm(
        coarse(np.array([[0.0, 0], [639, 479]])) - g(np.array([[0.0, 0], [639, 479]])), axis=1
    )
    assert off.max() > 2.5  # the flow has to bridge what the coarse model misses
    frame = frame_of_base(base, g, smooth_field, W, H)
    cfg = replace(FLOW, flow_preset="medium")
    reference = dense_flow.prepare_flow_reference(base, valid, 1.0)
    flow = dense_flow.frame_flow(frame, coarse, reference, cfg, point_step_px=48)
    q, b = flow.point_frame_xy, flow.point_base_xy
    assert len(q) >= 80
    b_true = g(q)
    for _ in range(30):
        b_true = g(q) - smooth_field(b_true)
    err = np.linalg.norm(b - b_true, axis=1)
    assert np.median(err) < 0.1 and np.percentile(err, 95) < 0.3, err
    f, stats = local.estimate_field_in_frame(frame, g, reference, cfg, flow=flow)
    nodes = f.node_xy.reshape(-1, 2)
    measured = f.valid.ravel()
    assert measured.sum() >= 20, stats.counts()
    err = np.linalg.norm(f.vectors.reshape(-1, 2)[measured] - smooth_field(nodes[measured]), axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.5, err


def test_field_in_frame_needs_the_flow_method_and_a_grey_frame():
    reference = dense_flow.prepare_flow_reference(
        np.zeros((50, 50), np.uint8), np.ones((50, 50), bool), 1
    )
    with pytest.raises(ValueError, match="needs method='flow', got 'sift'"):
        local.estimate_field_in_frame(np.zeros((40, 40), np.uint8), lambda q: q, reference)
    with pytest.raises(ValueError, match=r"frame_grey must be a \(H, W\) uint8 image"):
        local.estimate_field_in_frame(np.zeros((40, 40, 3), np.uint8), lambda q: q, reference, FLOW)


def sequential_reqcon(pos, disp, centre, cfg):
    """The documented REQCON of one cell written plainly (lstsq, one cell at a time), without the
    rival-motion guard: (vector or None, kept)."""
    idx = np.arange(len(disp))
    if len(idx) < cfg.min_matches:
        return None, np.zeros(len(disp), bool)
    while True:
        rel, d = pos[idx] - centre, disp[idx]
        spread = np.sqrt(np.linalg.eigvalsh(np.cov(rel.T))).min() if len(idx) > 2 else 0.0
        if cfg.cell_model == "affine" and len(idx) >= 6 and spread >= cfg.cell_px / 8:
            a = np.c_[np.ones(len(idx)), rel]
            coef = np.linalg.lstsq(a, d, rcond=None)[0]
            v, pred = coef[0], a @ coef
        else:
            v, pred = d.mean(axis=0), d.mean(axis=0)
        r = np.linalg.norm(d - pred, axis=1)
        if r.mean() < cfg.reqcon_target_px and r.max() <= cfg.reqcon_max_residual_px:
            kept = np.zeros(len(disp), bool)
            kept[idx] = True
            return v, kept
        n_keep = len(idx) - max(1, int(np.ceil(cfg.reqcon_drop_fraction * len(idx))))
        if n_keep < cfg.min_matches:
            kept = np.zeros(len(disp), bool)
            kept[idx] = True
            return None, kept
        idx = idx[np.sort(np.argsort(r, kind="stable")[:n_keep])]


def test_worst_kept_breaks_ties_as_a_stable_sort(rng):
    """REQCON drops each cell's worst kept matches; among equal residuals the lower slot goes
    first, as the stable sort it replaced did, also when the tie straddles the partition's
    boundary (rows 0 and 1 hold exact ties there; row 2 fewer kept slots than the most any row
    drops)."""
    from registration.local.consensus import _worst_kept

    r = rng.uniform(0, 1, (3, 12))
    r[0, [2, 5, 9]] = 2.0  # three-way tie for the two worst
    r[1, [1, 4]] = 3.0
    r[1, [3, 7, 8]] = 2.5  # the second worst tied three ways
    kept = np.ones((3, 12), bool)
    kept[1, 8] = False
    kept[2, 3:] = False
    n_drop = np.array([2, 3, 2])
    got = _worst_kept(r, kept, n_drop)
    for i in range(3):
        order = np.argsort(np.where(kept[i], -r[i], np.inf), kind="stable")[: n_drop[i]]
        np.testing.assert_array_equal(got[i, : n_drop[i]], order)
        assert (got[i, n_drop[i] :] == -1).all()
    np.testing.assert_array_equal(got[0, :2], [2, 5])
    np.testing.assert_array_equal(got[1, :3], [1, 4, 3])


def test_batched_consensus_equals_one_cell_at_a_time(rng):
    """consensus_cells decides every cell as a plain one-cell-at-a-time REQCON does, and as
    cell_consensus does on that cell alone (with the rival-motion guard)."""
    cells, members, pos, disp = [], [], [], []
    n = 0
    for _ in range(40):
        m = int(rng.integers(3, 120))
        centre = rng.uniform(0, 1000, 2)
        p = centre + rng.uniform(-100, 100, (m, 2))
        d = rng.normal(0, 0.2, (m, 2)) + rng.uniform(-3, 3, 2) + 0.004 * (p - centre)
        bad = rng.random(m) < rng.uniform(0, 0.6)  # outliers and, in some cells, a rival motion
        d[bad] += rng.choice([rng.uniform(-8, 8, 2), [0.0, 6.0]], axis=0) + rng.normal(
            0, 0.1, (bad.sum(), 2)
        )
        cells.append(centre)
        members.append(np.arange(n, n + m))
        pos.append(p)
        disp.append(d)
        n += m
    pos, disp = np.concatenate(pos), np.concatenate(disp)
    padded = np.full((len(cells), max(len(m) for m in members)), -1)
    for c, m in enumerate(members):
        padded[c, : len(m)] = m
    statuses = set()
    for model in ("translation", "affine"):
        cfg = replace(FLOW, cell_model=model, reqcon_target_px=0.3, reqcon_max_residual_px=1.0)
        vec, kept, resid, status = local.consensus_cells(pos, disp, np.array(cells), padded, cfg)
        for c, m in enumerate(members):
            one = local.cell_consensus(pos[m], disp[m], cells[c], cfg)
            assert one.status == status[c]
            statuses.add(int(one.status))
            assert (one.kept == kept[c, : len(m)]).all()
            np.testing.assert_allclose(one.vector, vec[c], atol=1e-9)
        unguarded = replace(cfg, rival_ratio=0)
        vec, kept, _, status = local.consensus_cells(pos, disp, np.array(cells), padded, unguarded)
        for c, m in enumerate(members):
            v, k = sequential_reqcon(pos[m], disp[m], cells[c], unguarded)
            assert (status[c] == OK) == (v is not None)
            assert (k == kept[c, : len(m)]).all()
            if v is not None:
                np.testing.assert_allclose(vec[c], v, atol=1e-9)
    # The random cells exercise success and every failure the consensus itself can report.
    assert {OK, NO_CONSENSUS, RIVAL_MOTION, local.FEW_MATCHES} <= statuses


# --------------------------------------------------------------------------------------------
# Spline fit (LocalConfig.fit = "spline")


def _corner_field(xy: np.ndarray) -> np.ndarray:
    """A field that bends within a 200 px cell, as a lens beyond Harris does towards a corner:
    quadratic plus a row-dependent shear (rolling shutter), up to ~6 px over 640x480."""
    u, v = xy[:, 0] / W, xy[:, 1] / H
    return np.c_[4.0 * u**2 + 0.8 * v, -3.0 * u * v + 1.5 * v**2 - 0.5]


def test_spline_recovers_a_bending_field_and_ignores_injected_mismatches(rng):
    """Template-like samples (every 25 px, 0.15 px noise) of a field that bends within a cell,
    with 5 % mismatches 4-8 px off at named indices: the spline puts zero weight on every
    mismatch and follows the field (measured 0.026 px mean, 0.076 max over the crop); the
    per-cell consensus of the previous reference field cannot follow the bend (0.109 px)."""
    gx, gy = np.meshgrid(np.arange(12.5, W, 25.0), np.arange(12.5, H, 25.0))
    pos = np.c_[gx.ravel(), gy.ravel()]
    disp = _corner_field(pos) + rng.normal(0, 0.15, pos.shape)
    bad = np.arange(0, len(pos), 20)
    angle = rng.uniform(0, 2 * np.pi, len(bad))
    disp[bad] += rng.uniform(4, 8, len(bad))[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    spline = LocalConfig(fit="spline", spacing_px=100, min_matches=6)
    field_, stats = local.estimate_field_spline(pos, disp, W, H, spline)
    probe = np.c_[rng.uniform(20, W - 20, 500), rng.uniform(20, H - 20, 500)]
    err = np.linalg.norm(field_.sample(probe) - _corner_field(probe), axis=1)
    assert err.mean() < 0.05 and err.max() < 0.15, (err.mean(), err.max())
    assert stats.n_valid >= 0.9 * stats.n_cells  # the nodes beyond the last samples: fewer
    assert int(stats.cell_kept.sum()) < int(stats.cell_matches.sum())  # the mismatches
    cells = LocalConfig(cell_model="affine", cell_px=300, spacing_px=150, min_matches=6,
                        reqcon_target_px=0.5, reqcon_max_residual_px=1.5)  # fmt: skip
    field_c, _ = local.estimate_field_from_matches(pos, disp, W, H, cells)
    err_c = np.linalg.norm(field_c.sample(probe) - _corner_field(probe), axis=1)
    assert err.mean() < 0.5 * err_c.mean(), (err.mean(), err_c.mean())


def test_spline_weights_drop_exactly_the_injected_mismatches(rng):
    """A constant shift with 0.1 px noise and mismatches 5 px off at indices 3, 50, 97 and
    140: the same field as without them (to 0.01 px), the mismatches carry no weight."""
    gx, gy = np.meshgrid(np.arange(10.0, 400, 20.0), np.arange(10.0, 300, 20.0))
    pos = np.c_[gx.ravel(), gy.ravel()]
    disp = np.tile([1.25, -0.5], (len(pos), 1)) + rng.normal(0, 0.1, pos.shape)
    cfg = LocalConfig(fit="spline", spacing_px=100)
    clean, _ = local.estimate_field_spline(pos, disp, 400, 300, cfg)
    dirty = disp.copy()
    dirty[[3, 50, 97, 140]] += [5.0, 0.0]
    field_, stats = local.estimate_field_spline(pos, dirty, 400, 300, cfg)
    assert np.abs(field_.vectors - clean.vectors).max() < 0.01
    assert int(stats.cell_matches.sum() - stats.cell_kept.sum()) >= 4


def test_spline_continues_the_slope_beyond_the_samples():
    """Samples of a linear field only in the middle of the crop: the nodes beyond them continue
    the slope exactly (the penalty's null space is affine), where a per-cell consensus repeats
    the last cell's vector; nodes without samples are marked as not measured."""
    gx, gy = np.meshgrid(np.arange(200.0, 441, 10.0), np.arange(150.0, 331, 10.0))
    pos = np.c_[gx.ravel(), gy.ravel()]

    def linear(xy):
        return np.c_[0.01 * xy[:, 0] - 2.0, 0.005 * xy[:, 1]]

    field_, stats = local.estimate_field_spline(pos, linear(pos), W, H, LocalConfig(fit="spline"))
    corners = np.array([[0.0, 0.0], [W - 1.0, 0.0], [0.0, H - 1.0], [W - 1.0, H - 1.0]])
    assert np.abs(field_.sample(corners) - linear(corners)).max() < 1e-3
    assert not field_.valid.all() and field_.valid.any()
    assert stats.counts()["outside"] == int((~field_.valid).sum() - stats.counts()["few_matches"])


def test_spline_with_too_few_samples_is_a_zero_unmeasured_field():
    field_, stats = local.estimate_field_spline(
        np.array([[10.0, 10.0], [20.0, 20.0]]), np.ones((2, 2)), 200, 200,
        LocalConfig(fit="spline", min_matches=6),
    )  # fmt: skip
    assert not field_.valid.any() and not np.asarray(field_.vectors).any()
    assert stats.n_valid == 0


def test_estimate_field_from_matches_dispatches_on_fit(rng):
    pos = np.c_[rng.uniform(0, W, 400), rng.uniform(0, H, 400)]
    disp = np.tile([0.5, 0.25], (400, 1))
    cfg = LocalConfig(fit="spline")
    a, _ = local.estimate_field_from_matches(pos, disp, W, H, cfg)
    b, _ = local.estimate_field_spline(pos, disp, W, H, cfg)
    assert np.array_equal(a.vectors, b.vectors) and np.array_equal(a.valid, b.valid)


def test_flow_refinement_iterations_and_patch_stride_reach_dis():
    from registration.matching import dis_flow

    medium = dis_flow(replace(FLOW, flow_preset="medium"))
    assert medium.getVariationalRefinementIterations() == 5 and medium.getPatchStride() == 3
    cfg = replace(FLOW, flow_preset="medium", flow_refinement_iterations=0, flow_patch_stride=4)
    assert dis_flow(cfg).getVariationalRefinementIterations() == 0
    assert dis_flow(cfg).getPatchStride() == 4


def test_local_lengths_grow_with_a_map_finer_than_the_frames():
    from registration.run import get_preset

    cfg = get_preset("default").local  # cells 200 base px every 100, above 1.5 base px/frame px
    assert cfg.for_base_scale(1.2) is cfg and cfg.for_base_scale(1.5) is cfg
    assert cfg.for_base_scale(0.5) is cfg  # a coarser map keeps them
    paper = get_preset("paper").local  # the paper's lengths whatever the map
    assert paper.for_base_scale(2.5) is paper
    finer = cfg.for_base_scale(2.38)
    assert (finer.cell_px, finer.spacing_px, finer.mask_erode_px) == (476, 238, 14)
    assert finer.max_displacement_px == pytest.approx(2.38 * cfg.max_displacement_px)
    assert finer.reqcon_target_px == pytest.approx(2.38 * cfg.reqcon_target_px)
    assert finer.neighbour_tolerance_px == pytest.approx(2.38 * cfg.neighbour_tolerance_px)
    # Flow samples are taken in the frame: their step and margin stay in frame px.
    assert (finer.flow_step_px, finer.flow_margin_px) == (cfg.flow_step_px, cfg.flow_margin_px)
    with pytest.raises(ValueError, match="base_scale_above must be None or >= 1, got 0.5"):
        replace(cfg, base_scale_above=0.5)


def test_the_reference_field_follows_a_map_finer_than_the_frames_too():
    """The pipeline derives every field's lengths from the reference frame's model: against a
    map at 2.38 base px per frame px the reference frame's (and anchors') spline nodes are
    238 base px apart, as the other frames' cells are (at 100 base px, ~3 template matches per
    node, its field followed their noise: paper-hard 1280x960 against a 2x map, motion after
    local 0.82 -> 0.42 base px); at 1.2 nothing changes."""
    from registration.geometry import Similarity
    from registration.lens import Camera
    from registration.run import get_preset
    from registration.run.pipeline import _at_base_resolution

    config = get_preset("default")
    camera = Camera(0.7, 640, 480)
    centre = camera.corrected_from_raw([[319.5, 239.5]])[0]
    for scale, spacing, cell in ((2.38, 238, 476), (1.2, 100, 200)):
        model = Similarity.from_rotation(217.0, scale, centre, (5000.0, 4000.0))
        derived = _at_base_resolution(config, camera, model)
        assert derived.reference_local.spacing_px == spacing
        assert (derived.local.cell_px, derived.local.spacing_px) == (cell, spacing)
    derived = _at_base_resolution(config, camera, model)
    assert derived.local is config.local and derived.reference_local is config.reference_local
    paper = get_preset("paper")  # the paper's lengths whatever the map
    big = Similarity.from_rotation(0.0, 3.0, centre, (5000.0, 4000.0))
    assert _at_base_resolution(paper, camera, big) is paper


def test_the_reference_field_bends_more_freely_beyond_harris():
    """The reference frame's (and anchors') own field takes the settings for the lens the
    reference frame's registration found: beyond Harris (a fourth-order term) the spline's
    smoothness is 0.05, with the lens exactly Harris 0.1; at any map resolution. Against the
    truth: tests/lens/test_lens_k2.py."""
    from registration.geometry import Similarity
    from registration.lens import Camera
    from registration.run import get_preset
    from registration.run.pipeline import _at_base_resolution

    config = get_preset("default")
    harris = Camera(0.7, 640, 480)
    centre = harris.corrected_from_raw([[319.5, 239.5]])[0]
    for scale, spacing in ((2.38, 238), (1.2, 100)):
        model = Similarity.from_rotation(217.0, scale, centre, (5000.0, 4000.0))
        for camera, smoothness in ((harris, 0.1), (harris.with_k2(0.033), 0.05)):
            derived = _at_base_resolution(config, camera, model)
            assert derived.reference_local.spline_smoothness == smoothness
            assert derived.reference_local.spacing_px == spacing
            assert derived.reference_local_beyond_harris is None
    assert config.reference_local_for(0.0) is config.reference_local
    assert config.reference_local_for(-0.01) is config.reference_local_beyond_harris
    paper = get_preset("paper")  # no field of its own, whatever the lens
    assert paper.reference_local_for(0.04) is None


def _fine_of(pos, disp):
    """A fine step's control points whose displacement under its (identity) model is ``disp``
    at base px ``pos``: what :func:`registration.local.reference_field` reads."""
    from types import SimpleNamespace

    from registration.geometry import Projective

    return SimpleNamespace(src=pos + disp, dst=pos, base_from_corrected=Projective())


def test_the_reference_field_is_kept_where_points_left_out_confirm_it(rng):
    """``support_folds``: a bending field sampled every 25 px with 0.15 px noise is confirmed by
    the points left out of each fold (measured 0.95) and kept to the bit; 160 control points
    whose displacements are noise alone (2.5 px, no field, as template matches against a map of
    another date can be) make a spline that follows the noise (measured 1.6 px RMS), which
    the points left out do not confirm (measured 0.006): not kept (zero vectors on its
    lattice, the true field)."""
    cfg = LocalConfig(fit="spline", spacing_px=100, min_matches=6)
    gx, gy = np.meshgrid(np.arange(12.5, W, 25.0), np.arange(12.5, H, 25.0))
    pos = np.c_[gx.ravel(), gy.ravel()]
    fine = _fine_of(pos, _corner_field(pos) + rng.normal(0, 0.15, pos.shape))
    plain, plain_stats = local.reference_field(fine, (W, H), cfg)
    kept, stats = local.reference_field(fine, (W, H), replace(cfg, support_folds=5))
    assert plain_stats.support_scale is None and stats.support_scale >= 0.9
    assert np.array_equal(kept.vectors, plain.vectors) and np.array_equal(kept.valid, plain.valid)

    pos = np.c_[rng.uniform(0, W, 160), rng.uniform(0, H, 160)]
    fine = _fine_of(pos, rng.normal(0, 2.5, pos.shape))
    plain, _ = local.reference_field(fine, (W, H), cfg)
    dropped, stats = local.reference_field(fine, (W, H), replace(cfg, support_folds=5))
    rms = float(np.sqrt(np.mean(np.sum(plain.vectors[plain.valid] ** 2, axis=-1))))
    assert rms > 0.5  # the spline followed the noise
    assert stats.support_scale < 0.2
    assert not dropped.vectors.any()
    assert dropped.origin == plain.origin and dropped.spacing == plain.spacing
    assert np.array_equal(dropped.valid, plain.valid)
    assert "support_scale" in stats.to_dict()


def test_the_reference_field_is_kept_at_the_nodes_points_left_out_confirm(rng):
    """Half a field: the left half of the frame's control points sample a bending field (0.15 px
    noise), the right half are noise alone (2.5 px, no field). The whole field is confirmed
    only 0.63 (measured): under 0.8, so each node is judged by its own cell's left-out points.
    The left half's nodes are kept (0.13 px from the truth there, measured; all zeros would be
    0.81) and the right half's are zero vectors (0.02 px; the whole field 0.85)."""
    cfg = LocalConfig(fit="spline", spacing_px=100, min_matches=6)
    gx, gy = np.meshgrid(np.arange(12.5, W, 25.0), np.arange(12.5, H, 25.0))
    pos = np.c_[gx.ravel(), gy.ravel()]
    left = pos[:, 0] < W / 2
    noise = np.where(left[:, None], rng.normal(0, 0.15, pos.shape), rng.normal(0, 2.5, pos.shape))
    truth = np.where(left[:, None], _corner_field(pos), 0.0)
    plain, _ = local.reference_field(_fine_of(pos, truth + noise), (W, H), cfg)
    field, stats = local.reference_field(
        _fine_of(pos, truth + noise), (W, H), replace(cfg, support_folds=5)
    )
    assert stats.support_scale < 0.8 and 0.2 < stats.support_nodes < 0.6, stats
    assert stats.to_dict()["support_nodes"] == stats.support_nodes
    tx, ty = np.meshgrid(np.arange(5, W, 10.0), np.arange(5, H, 10.0))
    at = np.c_[tx.ravel(), ty.ravel()]
    true_at = np.where((at[:, 0] < W / 2)[:, None], _corner_field(at), 0.0)
    inner_left, inner_right = at[:, 0] < W / 2 - 50, at[:, 0] > W / 2 + 50

    def error(f, where):
        return float(np.mean(np.hypot(*(f.sample(at[where], outside="clamp") - true_at[where]).T)))

    zero_left = float(np.mean(np.hypot(*true_at[inner_left].T)))
    assert error(field, inner_left) < 0.25 * zero_left, (error(field, inner_left), zero_left)
    assert error(field, inner_right) < 0.1 * error(plain, inner_right)


def test_support_folds_must_be_zero_or_two_and_more():
    with pytest.raises(ValueError, match="support_folds must be 0 or at least 2, got 1"):
        LocalConfig(support_folds=1)


def test_flow_correspondences_are_read_through_the_warps_lattice():
    """A raw frame taken through a γ = 0.6 Harris lens, the mid base image its exact source: the
    mid base image is warped into the frame through a lattice (nodes 8 px apart) that follows
    the lens's corners only to tenths of a px, so each sample's base point is read from that
    lattice, where the warp took the content the flow compares. Against the exact truth, median
    0.095 px at 0.6-0.85 of the half-diagonal, 0.249 px beyond (the model itself read at the
    sample: 0.130 and 0.345 px)."""
    from registration.lens import Camera
    from tests.matching.test_features import texture as aerial_texture
    from tests.matching.test_features import warp_into

    w, h = 320, 240
    camera = Camera(0.6, w, h)
    base = aerial_texture(700, 560, seed=3)

    def base_from_frame(q):
        return camera.corrected_from_raw(np.asarray(q, np.float64)) + (190.0, 160.0)

    frame = warp_into(base, base_from_frame, w, h)  # exact at every pixel (step 1)
    cfg = replace(FLOW, flow_preset="medium", flow_scale=1.0, flow_min_width_px=0, flow_step_px=8)
    reference = dense_flow.prepare_flow_reference(base, np.ones(base.shape, bool), 1.0)
    flow = dense_flow.frame_flow(frame, base_from_frame, reference, cfg)
    err = np.linalg.norm(base_from_frame(flow.frame_xy) - flow.base_xy, axis=1)
    r = np.hypot(*(flow.frame_xy - [(w - 1) / 2, (h - 1) / 2]).T) / np.hypot(w / 2, h / 2)
    middle, ring = (r >= 0.6) & (r < 0.85), r >= 0.85
    assert middle.sum() > 200 and ring.sum() > 30
    assert np.median(err[middle]) < 0.115, np.median(err[middle])  # measured 0.095
    assert np.median(err[ring]) < 0.3, np.median(err[ring])  # measured 0.249


def test_bilinear_weights_reproduce_the_field_inside_and_beyond_it():
    rng = np.random.default_rng(11)
    f = DisplacementField(
        (40.0, -20.0), 50.0, rng.normal(0, 1, (5, 7, 2)).astype(np.float32), np.ones((5, 7), bool)
    )
    # Points inside, beyond every edge, and on nodes.
    xy = np.r_[rng.uniform(-100, 500, (200, 2)), f.node_xy.reshape(-1, 2)]
    idx, w = f.bilinear(xy)
    assert idx.shape == w.shape == (len(xy), 4)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    flat = f.vectors.reshape(-1, 2).astype(np.float64)
    via_weights = np.einsum("nk,nkc->nc", w, flat[idx])
    np.testing.assert_allclose(via_weights, f.sample(xy, outside="clamp"), atol=1e-9)
