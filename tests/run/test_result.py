"""The result folder on its own (registration.run.result): hand-made folders with known models and
fields read back through the fixed interface (conventions.md), checked against formulas written
out here; failed, pending and damaged frames; the writer's records and arrays round trip."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import registration
from registration.geometry import DisplacementField, Projective
from registration.io import FrameSource
from registration.run import (
    FrameRecord,
    ResultWriter,
    frame_arrays,
    frame_stats,
    make_metadata,
    read_record,
    verify_record,
)

W, H = 160, 120
BASE = (400, 300)
GAMMA = 0.3
# Frame k's global model: corrected frame px -> base px.
MATRIX = np.array([[0.95, -0.12, 110.0], [0.10, 0.97, 60.0], [2e-5, -3e-5, 1.0]])
SHIFT = np.array([[40.0, 25.0], [0.0, 0.0], [-30.0, 10.0]])
FIELD_D = np.array([1.5, -0.75])  # frame 2's field: constant d(x) in base px


def harris_corrected_from_raw(q: np.ndarray, gamma: float = GAMMA) -> np.ndarray:
    """conventions.md, written out: raw -> corrected is the Harris formula with -gamma."""
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    r_n = np.hypot(W, H) / 2
    d = (q - c) / r_n
    rho2 = (d**2).sum(axis=1, keepdims=True)
    return c + r_n * d / np.sqrt(1 - gamma * rho2)


def expected_global(k: int, q: np.ndarray) -> np.ndarray:
    x = harris_corrected_from_raw(q)
    m = MATRIX.copy()
    m[:2, 2] += SHIFT[k]
    p = np.c_[x, np.ones(len(x))] @ m.T
    return p[:, :2] / p[:, 2:]


def model(k: int) -> Projective:
    m = MATRIX.copy()
    m[:2, 2] += SHIFT[k]
    return Projective.from_matrix(m)


def write_folder(out: Path, statuses=("ok", "failed", "ok", "ok")) -> Path:
    """A result folder of len(statuses) frames written by hand (not by ResultWriter); frame 2
    carries a constant field, frame 3 no record (pending) when its status is "pending"."""
    (out / "frames").mkdir(parents=True)
    meta = {
        "format": "aerialreg-result",
        "version": 1,
        "n_frames": len(statuses),
        "gamma": GAMMA,
        "frame_size": [W, H],
        "base_size": list(BASE),
        "reference_frame": 0,
    }
    (out / "result.json").write_text(json.dumps(meta))
    for k, status in enumerate(statuses):
        if status == "pending":
            continue
        rec = {"status": status, "reason": "" if status == "ok" else "test", "stats": {}}
        rec["model"] = model(k % 3).to_dict() if status == "ok" else None
        if k == 2:
            vectors = np.broadcast_to(FIELD_D, (3, 4, 2)).astype(np.float32)
            field = DisplacementField((0.0, 0.0), 150.0, vectors, np.ones((3, 4), bool))
            arrays = {f"field_{n}": v for n, v in field.to_arrays().items()}
            np.savez(out / "frames" / f"{k:06d}.npz", **arrays)
            rec["npz_bytes"] = (out / "frames" / f"{k:06d}.npz").stat().st_size
        (out / "frames" / f"{k:06d}.json").write_text(json.dumps(rec))
    return out


def raw_points() -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 7))
    return np.c_[gx.ravel(), gy.ravel()]


def test_global_stage_is_the_model_after_the_harris_correction(tmp_path):
    res = registration.load(write_folder(tmp_path / "r"))
    q = raw_points()
    for k in (0, 2):
        np.testing.assert_allclose(
            res.frame_to_base(k, q, "global"), expected_global(k, q), atol=1e-9
        )
        back = res.base_to_frame(k, expected_global(k, q), "global")
        np.testing.assert_allclose(back, q, atol=1e-6)
    # Frame 0 has no field: its local stage is its global one.
    np.testing.assert_array_equal(
        res.frame_to_base(0, q, "local"), res.frame_to_base(0, q, "global")
    )


def test_local_stage_applies_the_field_in_its_documented_direction(tmp_path):
    """``registered_local(x) = registered_global(x + d(x))`` (registration.local): with a
    constant field ``d``, frame_to_base(local) = frame_to_base(global) - d and
    base_to_frame(local)(b) = base_to_frame(global)(b + d)."""
    res = registration.load(write_folder(tmp_path / "r"))
    q = raw_points()
    assert res.field(2) is not None
    local = res.frame_to_base(2, q, "local")
    np.testing.assert_allclose(local, expected_global(2, q) - FIELD_D, atol=1e-3)
    b = expected_global(2, q)[10:20] - FIELD_D
    np.testing.assert_allclose(res.base_to_frame(2, b, "local"), q[10:20], atol=1e-3)
    np.testing.assert_allclose(
        res.base_to_frame(2, b, "local"), res.base_to_frame(2, b + FIELD_D, "global"), atol=1e-9
    )


def test_nan_where_nothing_is_known_and_errors_only_for_bad_arguments(tmp_path):
    res = registration.load(write_folder(tmp_path / "r", ("ok", "failed", "ok", "pending")))
    assert [res.status(k) for k in range(4)] == ["ok", "failed", "ok", "pending"]
    q = raw_points()
    for k in (1, 3):
        for stage in ("global", "local"):
            assert np.isnan(res.frame_to_base(k, q, stage)).all()
            assert np.isnan(res.base_to_frame(k, q + 100, stage)).all()
        assert res.model(k) is None
    # Outside the raw frame (beyond the outer pixels' edges): NaN, inside: finite.
    edge = np.array([[-0.6, 50.0], [W - 0.4, 50.0], [50.0, H - 0.4], [-0.4, -0.4], [W - 0.6, 3.0]])
    out = res.frame_to_base(0, edge, "global")
    assert np.isnan(out[:3]).all() and np.isfinite(out[3:]).all()
    # A base point whose frame position falls outside the frame: NaN.
    far = expected_global(0, np.array([[W + 40.0, H / 2]]))
    assert np.isnan(res.base_to_frame(0, far, "global")).all()
    with pytest.raises(IndexError, match="frame 4 out of range"):
        res.frame_to_base(4, q)
    with pytest.raises(ValueError, match="stage"):
        res.frame_to_base(0, q, "fine")


def test_unclipped_base_to_frame_carries_the_mapping_on_beyond_the_frames_edge(tmp_path):
    """``clip=False`` returns the raw px of base points that fall beyond the frame's edge (the
    formula's, global and local) instead of NaN; inside the frame both agree to the bit."""
    res = registration.load(write_folder(tmp_path / "r"))
    beyond = np.array([[W + 40.0, H / 2], [-20.0, 30.0], [50.0, H + 15.0], [-3.0, -2.0]])
    q = np.r_[raw_points(), beyond]
    for k, stage, shift in ((0, "global", 0.0), (2, "global", 0.0), (2, "local", FIELD_D)):
        b = expected_global(k, q) - shift
        clipped = res.base_to_frame(k, b, stage)
        unclipped = res.base_to_frame(k, b, stage, clip=False)
        assert np.isnan(clipped[-len(beyond) :]).all()
        np.testing.assert_allclose(unclipped, q, atol=1e-3)
        np.testing.assert_array_equal(unclipped[: -len(beyond)], clipped[: -len(beyond)])


def test_damaged_arrays_make_the_frame_damaged_not_an_exception(tmp_path):
    out = write_folder(tmp_path / "r")
    npz = out / "frames" / "000002.npz"
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    assert read_record(out, 2).status == "damaged"  # the size differs from its record
    res = registration.load(out)
    assert res.status(2) == "damaged"
    assert np.isnan(res.frame_to_base(2, raw_points(), "local")).all()
    # Same size, other bytes: found when the arrays are read.
    npz.write_bytes(data[:-8] + b"\0" * 8)
    res = registration.load(out)
    assert res.status(2) == "ok"
    assert np.isnan(res.frame_to_base(2, raw_points(), "local")).all()
    assert res.status(2) == "damaged"
    npz.unlink()
    assert "missing" in read_record(out, 2).reason


@dataclass
class _Fine:
    src: np.ndarray
    dst: np.ndarray
    kept: np.ndarray
    residuals: np.ndarray
    iterations: int = 3
    source: np.ndarray | None = None
    model_kind: str = "polyprojective"
    model_reason: str = "why"
    sigma_px: float = 0.4


@dataclass
class _Coarse:
    n_keypoints_frame: int = 100
    n_keypoints_base: int = 300
    n_matches: int = 50
    gated: np.ndarray = None
    n_inliers: int = 30
    model_kind: str = "affine"
    heading_deg: float | None = 12.3456
    scale: float | None = 1.25
    gate: str = "seed"


def test_writer_round_trip_of_records_arrays_and_stats(tmp_path):
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    import cv2

    for k in range(2):
        cv2.imwrite(str(frames_dir / f"{k:06d}.png"), np.full((H, W, 3), 50 * k, np.uint8))
    frames = FrameSource(frames_dir)
    base = np.zeros((BASE[1], BASE[0], 3), np.uint8)
    meta = make_metadata(frames, base, None, GAMMA, (1, 2, 3, 4), 0, _config(), "default")
    rng = np.random.default_rng(0)
    src, dst = rng.uniform(0, 100, (20, 2)), rng.uniform(0, 300, (20, 2))
    kept = np.arange(20) % 4 != 0
    fine = _Fine(src, dst, kept, rng.uniform(0, 2, 20), source=(np.arange(20) % 2))
    vectors = rng.normal(0, 1, (2, 3, 2)).astype(np.float32)
    field = DisplacementField((10.0, 20.0), 100.0, vectors, np.array([[1, 0, 1], [1, 1, 0]], bool))
    coarse = _Coarse(gated=np.arange(50) < 40)
    stats = frame_stats(coarse, fine, {"total": 1.234567})
    out = tmp_path / "out"
    with ResultWriter.create(out, meta, frames=frames) as writer:
        rec = FrameRecord("ok", stage="intra-sensor", stats=stats, model=model(0).to_dict())
        writer.write_frame(0, rec, frame_arrays(fine, field))
        writer.write_frame(1, FrameRecord.failed("no"))
    res = registration.load(out)
    assert res.meta["seed"] == [1.0, 2.0, 3.0, 4.0] and res.preset == "default"
    s, d, k, r = res.control_points(0)
    np.testing.assert_array_equal(s, src)
    np.testing.assert_array_equal(d, dst)
    np.testing.assert_array_equal(k, kept)
    f = res.field(0)
    np.testing.assert_array_equal(f.vectors, vectors)
    np.testing.assert_array_equal(f.valid, field.valid)
    assert f.origin == (10.0, 20.0) and f.spacing == 100.0
    st = res.records[0].stats
    assert (st["n_control_points"], st["n_inliers"], st["n_gated"]) == (20, 15, 40)
    assert st["residual_rms_px"] == pytest.approx(np.sqrt(np.mean(fine.residuals[kept] ** 2)))
    assert (st["coarse_model"], st["fine_model"], st["heading_deg"]) == (
        "affine",
        "polyprojective",
        12.346,
    )
    assert res.records[0].input_sha256 and res.records[0].npz_sha256
    assert res.status(1) == "failed" and res.control_points(1) is None
    # A changed array of the same size is found by its digest (what a resume checks).
    npz = out / "frames" / "000000.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    assert read_record(out, 0).status == "ok"
    assert verify_record(out, 0).status == "damaged"


def _config():
    from registration.run import get_preset

    return get_preset("default")


def test_a_result_folder_written_before_the_subpackages_loads_and_maps_as_it_did():
    """``tests/data/result_v1``: a 3-frame result written by the release before the library
    was split into subpackages (its ``expected.json`` says how), and the mappings that release
    computed from it: today's reader gives them to the last digits, at both stages."""
    folder = Path(__file__).resolve().parents[1] / "data" / "result_v1"
    expected = json.loads((folder / "expected.json").read_text())
    res = registration.load(folder)
    q = np.array(expected["points"])
    assert res.n_frames == len(expected["frames"]) == 3
    for k, exp in enumerate(expected["frames"]):
        assert res.status(k) == exp["status"] == "ok"
        assert isinstance(res.records[k], FrameRecord) and res.records[k].model is not None
        for stage in ("global", "local"):
            b = res.frame_to_base(k, q, stage)
            np.testing.assert_allclose(b, exp[f"frame_to_base_{stage}"], rtol=0, atol=1e-9)
            back = res.base_to_frame(k, b, stage)
            np.testing.assert_allclose(back, exp[f"base_to_frame_{stage}"], rtol=0, atol=1e-9)
    assert res.records[0].stage == "inter-sensor" and res.records[1].stage == "intra-sensor"
