"""``simulate`` never overwrites without ``force``, renders into a staging folder and writes the
truth last: a failed or killed run never leaves a truth beside frames of another run (issue 12)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from registration.synth import SimConfig, load_truth, simulate
from registration.synth import output as outmod
from registration.synth import sequence as seqmod

TINY = dict(frame_size=(96, 72), video=False)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _consistent(folder: Path) -> bool:
    """The folder's truth (if any) describes exactly the frames and base beside it."""
    if not (folder / "truth.json").exists():
        return True
    truth = load_truth(folder)
    frames = sorted(p.name for p in (folder / "frames").iterdir())
    return truth.verify_files() == [] and frames == [p.name for p in truth.frame_paths()]


def test_new_and_empty_folders_are_fine(tmp_path):
    simulate(tmp_path / "a" / "b", SimConfig(**TINY, n_frames=2))
    (tmp_path / "empty").mkdir()
    simulate(tmp_path / "empty", SimConfig(**TINY, n_frames=2))
    for d in ("a/b", "empty"):
        assert _consistent(tmp_path / d)
        assert not [p for p in (tmp_path / d).iterdir() if p.name.startswith(".")]


def test_foreign_folder_refused_then_force_replaces_only_owned_entries(tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "holiday.png").write_bytes(b"not a frame")
    (tmp_path / "notes.txt").write_text("keep me")
    before = _snapshot(tmp_path)
    with pytest.raises(FileExistsError) as info:
        simulate(tmp_path, SimConfig(**TINY, n_frames=2))
    msg = str(info.value)
    assert str(tmp_path) in msg and "not a simulator output" in msg and "\n" not in msg
    assert _snapshot(tmp_path) == before
    simulate(tmp_path, SimConfig(**TINY, n_frames=2), force=True)
    assert (tmp_path / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["000000.png", "000001.png"]
    assert _consistent(tmp_path)


def test_file_as_output_is_refused(tmp_path):
    f = tmp_path / "out"
    f.write_text("x")
    with pytest.raises(NotADirectoryError, match="exists and is not a folder"):
        simulate(f, SimConfig(**TINY, n_frames=2), force=True)
    assert f.read_text() == "x"


def test_writer_failure_mid_run_keeps_the_previous_run(tmp_path, monkeypatch):
    """A frame writer that dies at frame 2 of a --force rerun: the previous run is untouched
    (its truth still matches its frames) and the staging folder is gone."""
    simulate(tmp_path, SimConfig(**TINY, n_frames=4, seed=1))
    before = _snapshot(tmp_path)
    real = seqmod.write_png
    calls = []

    def dying(path, rgb):
        calls.append(path.name)
        if path.name == "000002.png":
            raise OSError("disk full (simulated)")
        return real(path, rgb)

    monkeypatch.setattr(seqmod, "write_png", dying)
    with pytest.raises(OSError, match="disk full"):
        simulate(tmp_path, SimConfig(**TINY, n_frames=3, seed=2), force=True)
    assert "000002.png" in calls
    assert _snapshot(tmp_path) == before
    assert _consistent(tmp_path) and load_truth(tmp_path).config["seed"] == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_kill_during_commit_leaves_no_truth_beside_other_frames(tmp_path, monkeypatch):
    """Interrupted while swapping the new entries in: the folder has no truth.json at all (the
    old one goes first, the new one last), so nothing pairs a truth with the wrong frames."""
    simulate(tmp_path, SimConfig(**TINY, n_frames=4, seed=1))
    real = os.replace
    moved = []

    def interrupted(src, dst):
        src, dst = Path(src), Path(dst)
        if tmp_path in (src.parent, dst.parent):  # a rename in the output folder itself
            moved.append(src.name if src.parent == tmp_path else f"->{dst.name}")
        if dst.name == "base.png" and dst.parent == tmp_path:
            raise KeyboardInterrupt  # as if killed between two renames
        return real(src, dst)

    monkeypatch.setattr(outmod.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        simulate(tmp_path, SimConfig(**TINY, n_frames=3, seed=2), force=True)
    monkeypatch.setattr(outmod.os, "replace", real)
    # The old truth left first; the interruption came after frames/ and base.png moved out.
    assert moved[0] == "truth.json" and "frames" in moved and "->frames" in moved
    assert not (tmp_path / "truth.json").exists()
    with pytest.raises(FileNotFoundError, match="no simulator truth"):
        load_truth(tmp_path)
    # The half-swapped folder is not a simulator output any more: refused without --force.
    with pytest.raises(FileExistsError):
        simulate(tmp_path, SimConfig(**TINY, n_frames=3, seed=2))
    simulate(tmp_path, SimConfig(**TINY, n_frames=3, seed=2), force=True)
    assert _consistent(tmp_path) and load_truth(tmp_path).n_frames == 3


def test_truth_is_the_last_file_written(tmp_path, monkeypatch):
    order = []
    real = outmod.write_bytes_atomic

    def record(path, data):
        order.append(Path(path).name)
        return real(path, data)

    monkeypatch.setattr(outmod, "write_bytes_atomic", record)
    simulate(tmp_path, SimConfig(**TINY, n_frames=3))
    assert order[-1] == "truth.json" and order.count("truth.json") == 1
    assert order[:-1] == ["base.png", "000000.png", "000001.png", "000002.png", "vehicles.csv"]


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigkill_mid_render_keeps_the_old_run_and_next_run_cleans_up(tmp_path):
    """A real kill -9 of ``aerialreg simulate --force`` while it renders over a previous run."""
    out = tmp_path / "seq"
    simulate(out, SimConfig(**TINY, n_frames=3, seed=1))
    before = _snapshot(out)
    code = "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            code,
            "simulate",
            str(out),
            "--force",
            "--size",
            "320x240",
            "--frames",
            "400",
            "--no-video",
            "--seed",
            "2",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            staged = list(out.glob(".simulate-*/frames/000003.png"))
            if staged:
                break
            assert proc.poll() is None, "the run ended before it could be killed"
            time.sleep(0.05)
        else:
            pytest.fail("no staged frames within 60 s")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(out.glob(".simulate-*")), "the killed run's staging folder is left behind"
    assert {k: v for k, v in _snapshot(out).items() if not k.startswith(".")} == before
    assert _consistent(out) and load_truth(out).config["seed"] == 1
    # The next run removes the dead run's staging folder.
    simulate(out, SimConfig(**TINY, n_frames=2, seed=3), force=True)
    assert not list(out.glob(".simulate-*"))
    assert _consistent(out) and load_truth(out).n_frames == 2


def test_truth_records_every_file_digest(tmp_path):
    simulate(tmp_path, SimConfig(**TINY, n_frames=2))
    data = json.loads((tmp_path / "truth.json").read_text())
    assert set(data["files"]) == {
        "base.png",
        "frames/000000.png",
        "frames/000001.png",
        "vehicles.csv",
    }
    truth = load_truth(tmp_path)
    assert truth.verify_files() == []
    (tmp_path / "frames" / "000001.png").write_bytes(b"changed")
    assert truth.verify_files() == ["frames/000001.png"]
