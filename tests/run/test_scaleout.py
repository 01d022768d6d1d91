"""Chunks and Dask (issue 15): the chunk plan, a run on a 2-worker ``LocalCluster`` that equals
the serial run with the same chunks, a Dask run killed with SIGKILL while chunks run and resumed,
the chunked run's accuracy against the simulator's truth, and the options' one-line errors.

The sequence has its reference frame in the middle, so chunks run forwards and backwards."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import registration
from app.cli import main as cli_main
from registration.io import open_frames, read_image
from registration.lens import Camera
from registration.run import (
    ANCHOR_STAGE,
    ChunkContext,
    ChunkJob,
    SerialExecutor,
    chunk_plan,
    get_preset,
    processing_order,
    register_sequence,
)
from registration.synth import PROFILES, SimConfig, load_truth, simulate

distributed = pytest.importorskip("distributed", reason="needs dask[distributed] (test extra)")

REPO = Path(__file__).resolve().parents[2]
W, H, N, REF, CHUNK = 480, 360, 12, 6, 4


# ------------------------------------------------------------------------------------------
# The chunk plan


@pytest.mark.parametrize(
    ("n", "ref", "m"), [(12, 6, 4), (12, 0, 5), (12, 11, 3), (7, 3, 1), (30, 10, 100)]
)
def test_chunk_plan_covers_every_frame_once_in_runs_towards_the_reference(n, ref, m):
    chunks = chunk_plan(n, ref, m)
    frames = [k for c in chunks for k in c.frames]
    assert sorted(frames) == sorted(set(range(n)) - {ref})
    order = processing_order(n, ref)
    for c in chunks:
        assert 1 <= len(c.frames) <= m
        steps = set(np.diff(c.frames)) if len(c.frames) > 1 else set()
        assert steps <= {1} or steps <= {-1}  # consecutive frames, one direction
        assert [k for k in order if k in c.frames] == list(c.frames)  # in processing order
        first = c.frames[0]
        assert c.follows_reference == (abs(first - ref) == 1)
    for direction in (+1, -1):  # lengths within a direction differ by one at most
        sizes = [len(c.frames) for c in chunks if (c.frames[0] - ref) * direction > 0]
        assert not sizes or max(sizes) - min(sizes) <= 1


def test_chunk_plan_zero_is_one_chain_in_processing_order():
    (chunk,) = chunk_plan(12, 6, 0)
    assert list(chunk.frames) == processing_order(12, 6)[1:] and chunk.follows_reference
    assert chunk_plan(1, 0, 0) == [] and chunk_plan(1, 0, 4) == []
    assert [c.frames for c in chunk_plan(12, 6, 4)] == [(7, 8, 9), (10, 11), (5, 4, 3), (2, 1, 0)]


def test_default_chunk_size_and_suites_agree_with_their_sources():
    import benchmarks
    from app.cli.commands import bench, register
    from registration.run import dask_executor

    assert register.DEFAULT_CHUNK_FRAMES == dask_executor.DEFAULT_CHUNK_FRAMES
    assert bench.SUITES == benchmarks.SUITES


# ------------------------------------------------------------------------------------------
# Serial and Dask runs


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scaleout") / "sim"
    simulate(out, SimConfig(frame_size=(W, H), n_frames=N, seed=11, video=False))
    return out


def _seed(sim: Path, ref: int = REF):
    truth = load_truth(sim)
    bx, by = truth.frame_to_base(ref, [[W / 2, H / 2]])[0]
    return (W / 2, H / 2, float(bx), float(by))


def _register(sim: Path, out: Path, chunk: int, **kwargs):
    config = dataclasses.replace(get_preset("default"), chunk_frames=chunk)
    return register_sequence(
        open_frames(sim / "frames"), read_image(sim / "base.png"), load_truth(sim).gamma, out,
        config=config, preset="default", seed=_seed(sim), reference_frame=REF, **kwargs,
    )  # fmt: skip


@pytest.fixture(scope="module")
def chunked(sim, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("chunked") / "out"
    _register(sim, out, CHUNK)
    return out


def _records(out: Path, n: int = N) -> dict:
    """Per frame: the record without timings and the arrays of its npz."""
    recs = {}
    for k in range(n):
        rec = json.loads((out / "frames" / f"{k:06d}.json").read_text())
        rec.get("stats", {}).pop("time_s", None)
        local = rec.get("stats", {}).get("local")
        if isinstance(local, dict):
            for key in [key for key in local if key.startswith("time")]:
                local.pop(key)
        npz = out / "frames" / f"{k:06d}.npz"
        recs[k] = (rec, dict(np.load(npz)) if npz.exists() else {})
    return recs


def _grid(n: int = 25) -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(0, W - 1, n), np.linspace(0, H - 1, round(n * H / W)))
    return np.c_[gx.ravel(), gy.ravel()]


def assert_same_result(a: Path, b: Path, n: int = N) -> None:
    """Every frame of ``b`` maps every point where ``a`` does, to 0.05 px (the requirement);
    the records and arrays are identical (what the runs deliver: bit-identical)."""
    ra, rb = registration.load(a), registration.load(b)
    grid = _grid()
    for k in range(n):
        assert ra.status(k) == rb.status(k), f"frame {k}"
        for stage in ("global", "local"):
            pa, pb = ra.frame_to_base(k, grid, stage), rb.frame_to_base(k, grid, stage)
            assert np.array_equal(np.isnan(pa), np.isnan(pb)), f"frame {k} {stage}"
            if not np.isnan(pa).all():
                gap = np.nanmax(np.hypot(*(pa - pb).T))
                assert gap <= 0.05, f"frame {k} {stage}: {gap:.3f} px apart"
    xa, xb = _records(a, n), _records(b, n)
    for k in range(n):
        assert xa[k][0] == xb[k][0], f"frame {k}: records differ"
        assert xa[k][1].keys() == xb[k][1].keys(), f"frame {k}"
        for name in xa[k][1]:
            assert np.array_equal(xa[k][1][name], xb[k][1][name], equal_nan=True), (k, name)
    assert (a / "mid_base.png").read_bytes() == (b / "mid_base.png").read_bytes()


def test_local_cluster_of_two_workers_gives_the_serial_result(sim, chunked, tmp_path):
    from registration.run import DaskExecutor, open_client

    seen = []
    with open_client(workers=2) as client:
        assert len(client.scheduler_info()["workers"]) == 2
        result = _register(sim, tmp_path / "dask", CHUNK, executor=DaskExecutor(client),
                           progress=lambda done, total: seen.append(done))  # fmt: skip
    assert all(result.status(k) == "ok" for k in range(N))
    assert seen[-1] == N and seen == sorted(seen) and len(set(seen)) >= N - 1  # frame by frame
    assert_same_result(chunked, tmp_path / "dask")


def test_chunked_run_is_as_accurate_as_one_chain(sim, chunked, tmp_path):
    """Chunk starts (frames 10 and 2 here) have no predecessor and are registered to the mid
    base image alone. Error against the truth over a 9x7 grid of every frame (stage local),
    measured: one chain mean 1.087 px (worst frame 1.35), chunks of 4 mean 1.090 px (worst
    1.39)."""
    one = _register(sim, tmp_path / "one", 0)
    truth, grid = load_truth(sim), _grid(9)

    def error(result):
        return np.array(
            [np.mean(np.hypot(*(result.frame_to_base(k, grid) - truth.frame_to_base(k, grid)).T))
             for k in range(N)]
        )  # fmt: skip

    res = registration.load(chunked)
    starts = [c.frames[0] for c in chunk_plan(N, REF, CHUNK) if not c.follows_reference]
    assert starts == [10, 2]
    assert all(res.records[k].stats.get("chunk_start") for k in starts)
    e_one, e_chunked = error(one), error(res)
    assert e_chunked.mean() <= 1.1 * e_one.mean() + 0.05, (e_one.round(2), e_chunked.round(2))
    assert e_chunked.max() < 2.0, e_chunked.round(2)


def test_a_repeated_frame_is_written_once(sim, chunked, tmp_path):
    """A chunk whose worker died is run again by Dask and sends its frames again: the driver
    keeps the first copy (the same, the run being deterministic)."""

    class Twice(SerialExecutor):
        def run(self, context, jobs, cancel=None):
            for out in super().run(context, jobs, cancel):
                yield out
                yield out

    written = []
    _register(sim, tmp_path / "twice", CHUNK, executor=Twice(),
              progress=lambda done, total: written.append(done))  # fmt: skip
    assert written[-1] == N and len(written) == len(set(written))
    assert_same_result(chunked, tmp_path / "twice")


# ------------------------------------------------------------------------------------------
# Killed and resumed


def _cli_args(sim: Path, out: Path) -> list[str]:
    fx, fy, bx, by = _seed(sim)
    return [
        sys.executable, "-m", "app.cli", "register", "--base", str(sim / "base.png"),
        "--frames", str(sim / "frames"), "--out", str(out), "--gamma", str(load_truth(sim).gamma),
        "--seed", f"{fx},{fy},{bx},{by}", "--reference-frame", str(REF),
    ]  # fmt: skip


def _done(out: Path) -> set[int]:
    folder = out / "frames"
    return {int(p.stem) for p in folder.glob("*.json")} if folder.is_dir() else set()


def _partial(done: set[int]) -> list:
    """The chunks of which some frames but not all are done."""
    return [c for c in chunk_plan(N, REF, CHUNK) if 0 < len(done & set(c.frames)) < len(c.frames)]


@pytest.mark.slow
def test_dask_run_killed_while_chunks_run_is_redone_on_resume(sim, chunked, tmp_path):
    """SIGKILL the driver once the reference frame and a few frames are written, while chunks
    are half done; its workers exit with it; ``--resume`` (taking the folder's chunk size) redoes
    what is missing and gives the uninterrupted serial run's result."""
    import psutil

    out = tmp_path / "out"
    cmd = [*_cli_args(sim, out), "--workers", "2", "--chunk-frames", str(CHUNK)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list = []
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 600 and proc.poll() is None:
            done = _done(out)
            if len(done) >= 3 and _partial(done):
                break
            time.sleep(0.02)
        workers = psutil.Process(proc.pid).children(recursive=True)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    done = _done(out)
    assert REF in done and len(done) < N and _partial(done), done
    gone, alive = psutil.wait_procs(workers, timeout=60)
    assert not alive, f"worker processes outlived the killed driver: {alive}"

    resumed = subprocess.run([*_cli_args(sim, out), "--resume", "--workers", "2"], cwd=REPO,
                             capture_output=True, text=True, timeout=900)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert json.loads((out / "result.json").read_text())["config"]["chunk_frames"] == CHUNK
    assert_same_result(chunked, out)


def test_cancelled_dask_run_keeps_its_frames_and_resumes_serially(sim, chunked, tmp_path):
    """Cancel (the app's stop button) after a few frames: the run returns with those frames
    written; resuming in this process, with the same chunks, completes the serial result."""
    from registration.run import DaskExecutor, open_client

    cancel = threading.Event()

    def progress(done, total):
        if done >= 4:
            cancel.set()

    out = tmp_path / "out"
    with open_client(workers=2) as client:
        _register(sim, out, CHUNK, executor=DaskExecutor(client), progress=progress,
                  cancel=cancel)  # fmt: skip
    done = _done(out)
    assert 4 <= len(done) < N, done
    _register(sim, out, CHUNK, resume=True)
    assert_same_result(chunked, out)


# ------------------------------------------------------------------------------------------
# A long flight in chunks: chunk starts off the mid base image, anchors replayed on resume


@pytest.mark.slow
def test_long_flight_in_chunks_stays_accurate_and_resumes_mid_chunk(tmp_path):
    """24 frames flying 1.5 footprints away from the reference frame (frame 0) in chunks of 6:
    the later chunks start off the mid base image, so their first frame is registered to the
    base map at any heading and becomes an anchor. Error against the truth over a 9x7 grid
    (stage local), measured: mean 1.012 px, worst frame 1.78 px (one chain: 1.031 and 1.58;
    an anchor whose fit lost its barrier put a pole in a corner: 3.94 px, see
    rational_fit._geometric_fun).
    A run resumed after frames at the end of each chunk were lost (anchors among the frames
    kept) gives the same models."""
    n, chunk = 24, 6
    sim = tmp_path / "sim"
    simulate(
        sim, PROFILES["long-flight"](frame_size=(W, H), n_frames=n, shake_deg=0.5, video=False)
    )
    truth = load_truth(sim)
    c = np.array([[W / 2, H / 2]])
    seed = (*c[0], *truth.frame_to_base(0, c)[0])
    config = dataclasses.replace(get_preset("default"), chunk_frames=chunk)

    def run(out, **kwargs):
        return register_sequence(
            open_frames(sim / "frames"), read_image(sim / "base.png"), truth.gamma, out,
            config=config, seed=seed, **kwargs,
        )  # fmt: skip

    result = run(tmp_path / "a")
    grid = _grid(9)
    err = np.array(
        [np.mean(np.hypot(*(result.frame_to_base(k, grid) - truth.frame_to_base(k, grid)).T))
         for k in range(n)]
    )  # fmt: skip
    assert all(result.status(k) == "ok" for k in range(n))
    assert err.max() < 2.5 and err.mean() < 1.3, err.round(2)
    starts = {k: result.records[k].stats.get("chunk_start") for k in (7, 13, 19)}
    assert "base map" in starts.values(), starts
    anchors = [k for k in range(n) if result.records[k].stage == ANCHOR_STAGE]
    assert anchors, "no anchor on a long flight"

    # Lose the last frames of each chunk, keeping its first frames and anchors among them.
    import shutil

    shutil.copytree(tmp_path / "a", tmp_path / "b")
    lost = [k for ch in chunk_plan(n, 0, chunk) for k in ch.frames[-2:]]
    assert any(a < k for a in anchors for k in lost)
    for k in lost:
        for suffix in (".json", ".npz"):
            (tmp_path / "b" / "frames" / f"{k:06d}{suffix}").unlink(missing_ok=True)
    run(tmp_path / "b", resume=True)
    ra, rb = registration.load(tmp_path / "a"), registration.load(tmp_path / "b")
    # Issue 12's bound (0.05 px). Not bit-identical here: with the spline field of the anchors,
    # a resumed chunk's first recomputed frame's fit differs in its last bits (measured: 6e-11 in
    # one coefficient of frame 18, cause not found; the short sequences of test_resume.py are
    # bit-identical).
    gaps = [
        np.nanmax(np.hypot(*(ra.frame_to_base(k, grid, s) - rb.frame_to_base(k, grid, s)).T))
        for k in range(n)
        for s in ("global", "local")
    ]
    assert max(gaps) <= 0.05, np.round(gaps, 4)


# ------------------------------------------------------------------------------------------
# Workers that do not see the driver's frames or code


def _context(sim: Path) -> ChunkContext:
    frames = open_frames(sim / "frames")
    z = np.zeros((4, 4, 3), np.uint8)
    camera = Camera(0.7, *frames.size)
    return ChunkContext(frames, z, None, camera, get_preset("default"), REF, {}, z,
                        np.zeros((4, 4), bool), frames.identity())  # fmt: skip


def test_worker_that_sees_other_frames_refuses_the_chunk(sim, tmp_path):
    from registration.run import check_frames

    ctx = _context(sim)
    job = ChunkJob(chunk_plan(N, REF, CHUNK)[0])
    check_frames(ctx, job)  # the same files: fine
    ctx.frames_identity["files"][8]["sample_sha256"] = "0" * 64
    with pytest.raises(ValueError, match=r"sees another frame 8 .* same files on every worker"):
        check_frames(ctx, job)
    ctx = _context(sim)
    ctx.frames = ctx.frames.resolved()
    ctx.frames._paths[REF] = tmp_path / "elsewhere" / "missing.png"
    with pytest.raises(ValueError, match=r"cannot read .*missing\.png.* storage every worker sees"):
        check_frames(ctx, job)


def test_worker_running_other_code_refuses_the_chunk(sim):
    from registration.run.dask_executor import _chunk_task

    with pytest.raises(ValueError, match="another version of aerialreg"):
        _chunk_task(_context(sim), ChunkJob(chunk_plan(N, REF, CHUNK)[0]), "q", "e", "0" * 64)


# ------------------------------------------------------------------------------------------
# The command line


def _refused(capsys, argv, needle: str) -> None:
    """The command exits with status 2 and one line on stderr holding ``needle`` (argparse's
    own errors included)."""
    try:
        code = cli_main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and needle in err, err


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--workers", "0"], "--workers must be 1..256, got 0"),
        (
            ["--workers", str((os.cpu_count() or 1) + 1)],
            f"is more than this machine's {os.cpu_count() or 1} CPU cores",
        ),
        (["--chunk-frames", "-3"], "--chunk-frames must be 0 (one chunk) or more, got -3"),
        (["--workers", "2", "--chunk-frames", "0"], "--workers and --scheduler need chunks"),
        (["--workers", "2", "--scheduler", "tcp://h:1"], "not allowed with argument --workers"),
        (["--workers", "two"], "invalid int value: 'two'"),
        (["--scheduler", " "], "--scheduler needs an address"),
    ],
)
def test_bad_scale_out_options_are_one_line_errors(sim, tmp_path, capsys, extra, needle):
    _refused(capsys, [*_cli_args(sim, tmp_path / "out")[3:], *extra], needle)
    assert not (tmp_path / "out").exists()


def test_resume_takes_the_folders_chunk_size_and_refuses_another(sim, chunked, tmp_path, capsys):
    import shutil

    out = tmp_path / "out"
    shutil.copytree(chunked, out)
    argv = _cli_args(sim, out)[3:]
    _refused(capsys, [*argv, "--resume", "--chunk-frames", "5"],
             f"cannot resume {out}: it was made with --chunk-frames {CHUNK}, not 5")  # fmt: skip
    assert cli_main([*argv, "--resume", "--json"]) == 0  # nothing left to do
    summary = json.loads(capsys.readouterr().out)
    assert summary["chunk_frames"] == CHUNK and summary["n_ok"] == N


def test_unreachable_scheduler_and_missing_dask_are_one_line_errors(sim, tmp_path, capsys,
                                                                    monkeypatch):  # fmt: skip
    from registration.run import dask_executor

    argv = _cli_args(sim, tmp_path / "out")[3:]
    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT_S", 2)
    _refused(capsys, [*argv, "--scheduler", "tcp://127.0.0.1:9"],
             "cannot connect to the Dask scheduler at tcp://127.0.0.1:9")  # fmt: skip
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    _refused(capsys, [*argv, "--workers", "2"], "pip install 'aerialreg[dask]'")
