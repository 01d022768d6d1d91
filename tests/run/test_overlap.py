"""Both cores busy within a chunk (registration/overlap.py, registration.run.intra_frames.run_chunk):
frames decoded ahead and the local stage in a second thread give the serial result to the bit,
through failed frames, re-anchored frames and jumps."""

from __future__ import annotations

import json
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from registration.global_registration import JointBase, add_to_mid_base
from registration.io import FrameReadError, open_frames
from registration.run import FramesAhead, LocalAhead, intra_frames
from registration.synth import SimConfig, simulate
from tests.conftest import register


def _frame_files(out: Path) -> dict[str, tuple[dict, dict]]:
    """Per frame: the JSON record without timings, and the arrays of its npz."""
    files = {}
    for path in sorted((out / "frames").glob("*.json")):
        rec = json.loads(path.read_text())
        stats = rec.get("stats", {})
        stats.pop("time_s", None)
        if isinstance(stats.get("local"), dict):
            for key in [key for key in stats["local"] if key.startswith("time")]:
                stats["local"].pop(key)
        npz = path.with_suffix(".npz")
        files[path.stem] = (rec, dict(np.load(npz)) if npz.exists() else {})
    return files


def _assert_same(a: Path, b: Path) -> None:
    """The same frames, registered in the same way, to the bit (records and arrays)."""
    fa, fb = _frame_files(a), _frame_files(b)
    assert fa.keys() == fb.keys()
    for name, (rec, arrays) in fa.items():
        assert rec == fb[name][0], name
        assert arrays.keys() == fb[name][1].keys(), name
        for key, value in arrays.items():
            assert np.array_equal(value, fb[name][1][key], equal_nan=True), (name, key)


def test_frames_ahead_returns_the_source_frames_and_its_errors(tmp_path):
    sim = tmp_path / "sim"
    simulate(sim, SimConfig(frame_size=(160, 120), n_frames=5, seed=4, video=False))
    (sim / "frames" / "000002.png").write_bytes(b"not a png")
    frames = open_frames(sim / "frames")
    with FramesAhead(frames, [0, 1, 2, 3, 4], depth=2) as ahead:
        assert len(ahead) == 5 and ahead.size == frames.size
        np.testing.assert_array_equal(ahead.get(0), frames.get(0))
        # Asked out of order (frame 1 skipped, frame 0 again): read directly, still right.
        np.testing.assert_array_equal(ahead.get(3), frames.get(3))
        np.testing.assert_array_equal(ahead.get(0), frames.get(0))
        np.testing.assert_array_equal(ahead.get(4), frames.get(4))
    with FramesAhead(frames, [1, 2, 3]) as ahead:
        ahead.get(1)
        with pytest.raises(FrameReadError, match="000002"):
            ahead.get(2)
        np.testing.assert_array_equal(ahead.get(3), frames.get(3))
    with pytest.raises(ValueError, match="depth"):
        FramesAhead(frames, [0], depth=0)


def test_local_ahead_hands_back_results_and_errors_in_order():
    for enabled in (True, False):
        with LocalAhead(enabled) as pool:
            pool.submit("a", lambda x: x * 2, 21)
            pool.submit("b", lambda: 1 / 0)
            assert pool.pending() == ["a", "b"]
            assert pool.result("a") == 42
            with pytest.raises(ZeroDivisionError):
                pool.result("b")


def test_local_ahead_runs_as_many_calls_at_once_as_it_has_workers():
    """Two calls that each wait for the other (a barrier of 2) finish with two workers; with
    one, the second cannot start while the first waits, and the first times out."""
    for workers, finishes in ((2, True), (1, False)):
        barrier = threading.Barrier(2, timeout=2)
        with LocalAhead(True, workers=workers) as pool:
            pool.submit("a", barrier.wait)
            pool.submit("b", barrier.wait)
            if finishes:
                assert {pool.result("a"), pool.result("b")} == {0, 1}
                continue
            with pytest.raises(threading.BrokenBarrierError):
                pool.result("a")
            with pytest.raises(threading.BrokenBarrierError):  # the barrier broke for it too
                pool.result("b")
    with LocalAhead(True, workers=2) as pool:
        gate = threading.Event()
        pool.submit("waits", gate.wait, 5)
        pool.submit("quick", int, 7)
        while not pool.done("quick"):
            gate.wait(0.01)
        assert not pool.done("waits")
        gate.set()
        assert pool.result("quick") == 7 and pool.result("waits") is True
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        LocalAhead(True, workers=0)


def test_local_ahead_close_drops_calls_not_started():
    """A run stopped early: the call running finishes, the one waiting for a worker never
    starts."""
    ran, gate = [], threading.Event()
    pool = LocalAhead(True, workers=1)
    pool.submit("running", gate.wait, 5)
    pool.submit("waiting", ran.append, 1)
    threading.Timer(0.2, gate.set).start()
    pool.close()
    assert gate.is_set() and ran == []


def test_overlap_gives_the_serial_result(sim_seq, default_result, tmp_path):
    # default_result overlaps (the default for a run in one process).
    serial = register(sim_seq, tmp_path / "serial", overlap=False)
    _assert_same(Path(default_result.out_dir), Path(serial.out_dir))


def test_overlapped_run_starts_the_next_local_stage_while_one_runs(
    sim_seq, default_result, monkeypatch, tmp_path
):
    """The first intra-sensor frame's local stage waits until the second one's starts: that
    happens only when the main thread went on to the next global stage without waiting for it
    and a second local worker took the next local stage. The result is unchanged."""
    second_started = threading.Event()
    calls: list[int] = []
    waited: list[bool] = []
    local_stage = intra_frames._local_stage

    def first_waits_for_second(*args):
        calls.append(1)
        if len(calls) == 1:
            waited.append(second_started.wait(20))
        else:
            second_started.set()
        return local_stage(*args)

    monkeypatch.setattr(intra_frames, "_local_stage", first_waits_for_second)
    overlapped = register(sim_seq, tmp_path / "overlapped", overlap=True)
    assert waited == [True] and len(calls) >= 3
    _assert_same(Path(default_result.out_dir), Path(overlapped.out_dir))


def test_joint_base_derives_a_value_once_for_concurrent_callers_and_drops_it_on_change():
    joint = JointBase(np.zeros((8, 8), np.uint8), np.ones((8, 8), bool))
    calls: list[int] = []

    def make():
        calls.append(1)
        time.sleep(0.2)  # both callers arrive while the first one makes it
        return object()

    with ThreadPoolExecutor(2) as pool:
        got = list(pool.map(lambda _: joint.derived.get("flow_reference", make), range(2)))
    assert calls == [1] and got[0] is got[1] is joint.derived.get("flow_reference", make)
    # A re-anchored frame over content already there changes nothing: the value stays.
    patch = np.full((2, 2), 9, np.uint8)
    add_to_mid_base(joint, patch, np.ones((2, 2), bool), (0, 0, 2, 2))
    assert joint.derived.get("flow_reference", make) is got[0] and calls == [1]
    # One that fills empty pixels changes the mid base image: every derived value is made anew.
    joint.mid_valid[:2, :2] = False
    add_to_mid_base(joint, patch, np.ones((2, 2), bool), (0, 0, 2, 2))
    assert joint.derived.get("flow_reference", make) is not got[0] and calls == [1, 1]


@pytest.fixture(scope="module")
def rough_sequence(tmp_path_factory) -> tuple[Path, Path]:
    """A slow flyover with frames 2-4 dropped (a 200+ px jump: the SIFT fallback, then an
    anchor) and an unreadable frame in the middle."""
    sim = tmp_path_factory.mktemp("rough") / "sim"
    simulate(
        sim,
        SimConfig(frame_size=(640, 480), n_frames=8, seed=2, video=False, flyover_footprints=0.3),
    )
    frames = sim.parent / "frames"
    frames.mkdir()
    for i, k in enumerate([0, 1, -1, 5, 6, 7]):
        if k < 0:
            (frames / f"{i:06d}.png").write_bytes(b"broken")
        else:
            shutil.copy(sim / "frames" / f"{k:06d}.png", frames / f"{i:06d}.png")
    return sim, frames


def test_overlap_gives_the_serial_result_through_failures_and_anchors(rough_sequence, tmp_path):
    sim, frames = rough_sequence
    a = register(sim, tmp_path / "a", frames_dir=frames, overlap=True)
    b = register(sim, tmp_path / "b", frames_dir=frames, overlap=False)
    stages = [r.stage or r.status for r in a.records]
    assert stages[2] == "failed" and "intra-sensor" in stages
    _assert_same(Path(a.out_dir), Path(b.out_dir))
