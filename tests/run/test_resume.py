"""Reproducible runs and exact resume (issue 12): two runs of ``aerialreg register`` in separate
processes give bit-identical result folders, and a run killed with SIGKILL at three moments and
resumed gives the uninterrupted run's result; the reference frame sits in the middle of the
sequence so that frames are registered forwards and backwards."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import registration
from registration.synth import SimConfig, load_truth, simulate

REPO = Path(__file__).resolve().parents[2]
N_FRAMES = 7
REF = 3


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("resume") / "sim"
    simulate(out, SimConfig(frame_size=(480, 360), n_frames=N_FRAMES, seed=7, video=False))
    return out


def _args(sim: Path, out: Path) -> list[str]:
    truth = load_truth(sim)
    w, h = truth.frame_size
    bx, by = truth.frame_to_base(REF, [[w / 2, h / 2]])[0]
    return [
        sys.executable, "-m", "app.cli", "register", "--base", str(sim / "base.png"),
        "--frames", str(sim / "frames"), "--out", str(out), "--gamma", str(truth.gamma),
        "--seed", f"{w / 2},{h / 2},{bx},{by}", "--reference-frame", str(REF),
    ]  # fmt: skip


def _register(sim: Path, out: Path, *extra: str) -> None:
    proc = subprocess.run(
        [*_args(sim, out), *extra], cwd=REPO, capture_output=True, text=True, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


def _records(out: Path) -> dict[int, tuple[dict, dict]]:
    """Per frame: the JSON record without timings, and the arrays of its npz."""
    recs = {}
    for k in range(N_FRAMES):
        rec = json.loads((out / "frames" / f"{k:06d}.json").read_text())
        rec.get("stats", {}).pop("time_s", None)
        local = rec.get("stats", {}).get("local")
        if isinstance(local, dict):  # the local stage's own timings
            for key in [key for key in local if key.startswith("time")]:
                local.pop(key)
        npz = out / "frames" / f"{k:06d}.npz"
        arrays = dict(np.load(npz)) if npz.exists() else {}
        recs[k] = (rec, arrays)
    return recs


@pytest.fixture(scope="module")
def uninterrupted(sim, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("full") / "out"
    _register(sim, out)
    return out


@pytest.mark.slow
def test_two_runs_are_bit_identical(sim, uninterrupted, tmp_path):
    again = tmp_path / "again"
    _register(sim, again)
    a, b = _records(uninterrupted), _records(again)
    for k in range(N_FRAMES):
        assert a[k][0] == b[k][0], f"frame {k}: records differ"
        assert a[k][1].keys() == b[k][1].keys()
        for name in a[k][1]:
            assert np.array_equal(a[k][1][name], b[k][1][name], equal_nan=True), (
                f"frame {k}: {name} differs"
            )


def _kill_after(sim: Path, out: Path, n_records: int) -> None:
    """Start a run and SIGKILL it once ``n_records`` frame records exist."""
    proc = subprocess.Popen(_args(sim, out), cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 600:
            done = len(list((out / "frames").glob("*.json"))) if (out / "frames").is_dir() else 0
            if done >= n_records or proc.poll() is not None:
                break
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)


@pytest.mark.slow
@pytest.mark.parametrize("n_records", [1, 3, 5])
def test_killed_and_resumed_run_equals_the_uninterrupted_one(sim, uninterrupted, tmp_path,
                                                             n_records):  # fmt: skip
    """Killed after the reference frame (1 record), after frames forwards (3) and while going
    backwards (5): the resumed folder maps every point of every frame where the uninterrupted
    one does, to 0.05 px or better (measured: identically)."""
    out = tmp_path / "out"
    _kill_after(sim, out, n_records)
    _register(sim, out, "--resume")
    a, b = registration.load(uninterrupted), registration.load(out)
    truth = load_truth(sim)
    w, h = truth.frame_size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 25), np.linspace(0, h - 1, 19))
    grid = np.c_[gx.ravel(), gy.ravel()]
    for k in range(N_FRAMES):
        assert a.records[k].status == b.records[k].status == "ok"
        for stage in ("global", "local"):
            pa, pb = a.frame_to_base(k, grid, stage), b.frame_to_base(k, grid, stage)
            assert np.array_equal(np.isnan(pa), np.isnan(pb))
            gap = np.nanmax(np.hypot(*(pa - pb).T))
            assert gap <= 0.05, f"frame {k} {stage}: {gap:.3f} px from the uninterrupted run"
        # The links measured as frames were registered: the resumed chunk read again the frames
        # it had that its next frames link to (registration.run.chunk_links).
        la, lb = a.stored_links(k), b.stored_links(k)
        assert la.keys() == lb.keys() and (la or k == REF), (k, sorted(la), sorted(lb))
        assert all(np.array_equal(la[n], lb[n]) for n in la), k


@pytest.fixture(scope="module")
def uninterrupted_adjusted(sim, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("full_adjusted") / "out"
    _register(sim, out, "--adjust")
    return out


@pytest.mark.slow
def test_killed_while_adjusting_resumes_to_the_same_bits(sim, uninterrupted_adjusted, tmp_path):
    """SIGKILL once every frame is registered, as the sequence adjustment starts (or while it
    writes): the resumed run's records and arrays equal the uninterrupted run's."""
    out = tmp_path / "out"
    proc = subprocess.Popen([*_args(sim, out), "--adjust"], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 600 and proc.poll() is None:
            records = list((out / "frames").glob("*.json")) if (out / "frames").is_dir() else []
            if len(records) == N_FRAMES:
                break
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    _register(sim, out, "--adjust", "--resume")
    a, b = _records(uninterrupted_adjusted), _records(out)
    for k in range(N_FRAMES):
        assert "adjustment" in a[k][0]["stats"]
        assert a[k][0] == b[k][0], f"frame {k}: records differ"
        assert a[k][1].keys() == b[k][1].keys()
        for name in a[k][1]:
            assert np.array_equal(a[k][1][name], b[k][1][name], equal_nan=True), (k, name)
