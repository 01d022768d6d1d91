"""Bad input for every command (register, evaluate, undistort, calibrate, simulate, app, bench)
and the result folder's guarantees: no silent mixing of inputs, no data loss, no way around the
limits.

Each refused case asserts the exit status 2, exactly one line ``aerialreg COMMAND: error: ...``
on standard error (progress-bar lines aside) naming the problem, no traceback, and that no file
that existed before was changed. Cases the run survives (a corrupt frame, a damaged record)
assert what the result says about them.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

import registration
from app.cli import main as cli_main
from registration.io import MAX_FRAME_PIXELS, open_frames, read_image
from registration.run import ResultLock, get_preset, register_sequence
from registration.synth import SimConfig, load_truth, simulate

REPO = Path(__file__).resolve().parents[2]
N = 6
SIZE = (480, 360)
PROGRESS = re.compile(r"^[\w ()]+: \d+/\d+ \(\d+%\)")


# ------------------------------------------------------------------------------------------
# helpers


def cli(capsys, *argv) -> tuple[int, str, str]:
    try:
        code = cli_main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(code: int, err: str, command: str, *needles: str) -> str:
    """Exit 2, one error line naming ``needles``, no traceback; returns the line."""
    lines = [ln for ln in err.splitlines() if ln.strip() and not PROGRESS.match(ln)]
    assert "Traceback" not in err, err
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"aerialreg {command}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def snapshot(*roots: Path) -> dict[Path, tuple[int, int, str]]:
    """Every file under ``roots``: size, mtime and SHA-256 (not the result folder's ``.lock``,
    which each process that takes the lock stamps with its pid)."""
    files = {}
    for root in roots:
        root = Path(root)
        paths = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
        for p in paths:
            if p.name == ".lock":
                continue
            st = p.stat()
            files[p] = (st.st_size, st.st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
    return files


def assert_unchanged(before: dict, *, no_new_under: Path | None = None) -> None:
    after = snapshot(*{p.parent for p in before}) if before else {}
    for p, stamp in before.items():
        assert p.exists(), f"{p} was deleted"
        assert snapshot(p)[p] == stamp, f"{p} was changed"
    if no_new_under is not None:
        new = [p for p in after if p not in before and no_new_under in p.parents]
        assert not new, f"new files: {new}"


def png_header_only(path: Path, w: int, h: int) -> Path:
    """A structurally valid PNG declaring ``w`` x ``h`` pixels with one row of data: a
    decompression bomb as far as any decoder is concerned (tiny file, huge image)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    data = (
        chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * (w + 1))) + chunk(b"IEND", b"")
    )
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + data)
    return path


def truncate(path: Path, fraction: float = 0.5) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def sparse_file(path: Path, size: int) -> Path:
    with open(path, "wb") as f:
        f.truncate(size)
    return path


# ------------------------------------------------------------------------------------------
# fixtures


@pytest.fixture(scope="module")
def sims(tmp_path_factory) -> tuple[Path, Path]:
    """Two simulated sequences of the same shape (6 frames 480x360) over different ground."""
    root = tmp_path_factory.mktemp("sims")
    for name, seed in (("A", 1), ("B", 2)):
        simulate(root / name, SimConfig(frame_size=SIZE, n_frames=N, seed=seed, video=False))
    return root / "A", root / "B"


def register_args(sim: Path, out: Path, frames: Path | None = None) -> list[str]:
    return [
        "register",
        "--base",
        sim / "base.png",
        "--frames",
        frames or sim / "frames",
        "--out",
        out,
        "--gamma",
        "0.7",
    ]


@pytest.fixture(scope="module")
def registered(sims, tmp_path_factory) -> Path:
    """sequence A registered with the CLI's defaults."""
    out = tmp_path_factory.mktemp("reg") / "out"
    assert cli_main([str(a) for a in register_args(sims[0], out)]) == 0
    return out


def copy_result(registered: Path, tmp_path: Path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(registered, out)
    return out


def copy_frames(sim: Path, tmp_path: Path) -> Path:
    frames = tmp_path / "frames"
    shutil.copytree(sim / "frames", frames)
    return frames


def truth_error(result, truth, k: int) -> float:
    w, h = SIZE
    gx, gy = np.meshgrid(np.linspace(60, w - 60, 5), np.linspace(60, h - 60, 4))
    q = np.c_[gx.ravel(), gy.ravel()]
    return float(
        np.median(np.linalg.norm(result.frame_to_base(k, q) - truth.frame_to_base(k, q), axis=1))
    )


# ------------------------------------------------------------------------------------------
# register: no silent mixing of inputs


def test_resume_with_another_frames_folder_of_the_same_shape_is_refused(
    sims, registered, tmp_path, capsys
):
    out = copy_result(registered, tmp_path)
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out, sims[1] / "frames"), "--resume")
    assert_refused(
        code,
        err,
        "register",
        f"cannot resume {out}",
        "frame 0",
        "differs from the run's input",
        "--force",
    )
    assert_unchanged(before, no_new_under=out)


def test_resume_after_a_frame_was_replaced_names_that_frame(sims, tmp_path, capsys):
    frames = copy_frames(sims[0], tmp_path)
    out = tmp_path / "out"
    assert cli(capsys, *register_args(sims[0], out, frames))[0] == 0
    shutil.copy(sims[1] / "frames" / "000004.png", frames / "000004.png")
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out, frames), "--resume")
    assert_refused(code, err, "register", "frame 4", "000004.png", "bytes")
    assert_unchanged(before)


def test_resume_sees_a_change_inside_a_frame_that_keeps_its_size(sims, tmp_path, capsys):
    """Size and first/last 64 KB unchanged, mtime changed: the frame, registered before, is
    hashed whole against its record."""
    frames = copy_frames(sims[0], tmp_path)
    out = tmp_path / "out"
    assert cli(capsys, *register_args(sims[0], out, frames))[0] == 0
    path = frames / "000002.png"
    data = bytearray(path.read_bytes())
    assert len(data) > 3 * 64 * 1024
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    code, _, err = cli(capsys, *register_args(sims[0], out, frames), "--resume")
    assert_refused(code, err, "register", "frame 2", "content changed since it was registered")


def test_resume_accepts_copied_and_touched_frames(sims, registered, tmp_path, capsys):
    """Same content under new mtimes (a copy without -p, a touch) is the same input."""
    out = copy_result(registered, tmp_path)
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in sorted((sims[0] / "frames").glob("*.png")):
        shutil.copyfile(p, frames / p.name)  # new mtimes
    records = snapshot(out / "frames")
    code, _, err = cli(capsys, *register_args(sims[0], out, frames), "--resume")
    assert code == 0, err
    assert_unchanged(records)  # nothing redone


def test_resume_with_another_base_map_of_the_same_size_is_refused(
    sims, registered, tmp_path, capsys
):
    out = copy_result(registered, tmp_path)
    base = read_image(sims[0] / "base.png")
    base[100:140, 100:140] = 255 - base[100:140, 100:140]
    cv2.imwrite(str(tmp_path / "base.png"), base)
    code, _, err = cli(
        capsys,
        "register",
        "--base",
        tmp_path / "base.png",
        "--frames",
        sims[0] / "frames",
        "--out",
        out,
        "--gamma",
        "0.7",
        "--resume",
    )
    assert_refused(code, err, "register", "the base map", "other pixels")


def test_resume_of_a_result_without_input_identity_is_refused(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    meta = json.loads((out / "result.json").read_text())
    del meta["inputs"]
    (out / "result.json").write_text(json.dumps(meta))
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
    assert_refused(code, err, "register", "no record of its inputs", "--force")
    assert_unchanged(before)


def test_library_resume_with_other_frames_raises_one_line(sims, registered, tmp_path):
    out = copy_result(registered, tmp_path)
    with pytest.raises(ValueError, match="cannot resume") as exc:
        register_sequence(
            open_frames(sims[1] / "frames"),
            read_image(sims[0] / "base.png"),
            0.7,
            out,
            config=get_preset("default"),
            preset="default",
            resume=True,
        )
    assert "\n" not in str(exc.value)


# ------------------------------------------------------------------------------------------
# register: the lock


def _hold_lock(out: Path) -> subprocess.Popen:
    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from registration.run.result_folder import ResultLock\n"
        "ResultLock(Path(sys.argv[1])).acquire()\n"
        "print('locked', flush=True)\n"
        "time.sleep(120)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, env=env, text=True
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_second_writer_fails_at_once_and_a_killed_writer_does_not_block(
    sims, registered, tmp_path, capsys
):
    out = copy_result(registered, tmp_path)
    holder = _hold_lock(out)
    try:
        before = snapshot(out)
        code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
        line = assert_refused(
            code,
            err,
            "register",
            "is being written by another aerialreg process",
            "wait for it or use another --out",
        )
        assert f"pid {holder.pid}" in line
        assert_unchanged(before)
        code, _, err = cli(capsys, *register_args(sims[0], out), "--force")
        assert_refused(code, err, "register", "being written by another")
        assert_unchanged(before)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # The kernel released the killed process's lock: the next run goes ahead.
    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
    assert code == 0, err


def test_lock_is_exclusive_within_one_process(registered, tmp_path):
    """The app runs registrations in threads of one process: two writers still exclude."""
    out = copy_result(registered, tmp_path)
    first = ResultLock(out).acquire()
    try:
        with pytest.raises(ValueError, match="being written by another aerialreg process"):
            ResultLock(out).acquire()
    finally:
        first.release()
    ResultLock(out).acquire().release()


# ------------------------------------------------------------------------------------------
# register: --out and --force


def test_out_that_is_a_file(sims, tmp_path, capsys):
    target = tmp_path / "notes.txt"
    target.write_text("keep me\n")
    before = snapshot(target)
    code, _, err = cli(capsys, *register_args(sims[0], target))
    assert_refused(code, err, "register", "exists and is a file", str(target))
    assert_unchanged(before)


@pytest.mark.parametrize("force", [False, True])
def test_out_that_is_another_tools_folder_is_refused_even_with_force(sims, tmp_path, capsys, force):
    """A simulator folder (frames/, base.png, truth.json) must never be written into or deleted."""
    folder = tmp_path / "sim"
    shutil.copytree(sims[0], folder)
    before = snapshot(folder)
    code, _, err = cli(capsys, *register_args(sims[0], folder), *(["--force"] if force else []))
    assert_refused(code, err, "register", "is not an aerialreg result folder", "base.png")
    assert_unchanged(before, no_new_under=folder)
    assert not (folder / ".lock").exists()


def test_existing_result_needs_resume_or_force(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out))
    assert_refused(
        code, err, "register", "already holds a registration result", "--resume", "--force"
    )
    assert_unchanged(before)


def test_resume_and_force_exclude_each_other(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume", "--force")
    assert_refused(code, err, "register", "--resume and --force exclude each other")
    assert_unchanged(before)


def test_force_starts_over_and_keeps_other_files(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    (out / "my-notes.txt").write_text("mine\n")
    (out / "frames" / "000000.png").write_bytes(b"not ours")  # not a record: kept
    # Dot-files ending in .tmp that are not temporary files of the result's own names: kept.
    users = [out / ".notes.tmp", out / ".draft.abcd1234.tmp", out / "frames" / ".x.y.tmp"]
    for p in users:
        p.write_text("mine\n")
    own_temp = out / "frames" / ".000001.json.k2x9_a7q.tmp"  # a killed write of a record
    own_temp.write_text("{")
    keep = snapshot(out / "my-notes.txt", out / "frames" / "000000.png", *users)
    frames = copy_frames(sims[0], tmp_path)
    (frames / "000005.png").unlink()  # a different input: 5 frames
    old_records = snapshot(out / "frames")
    code, _, err = cli(capsys, *register_args(sims[0], out, frames), "--force")
    assert code == 0, err
    assert_unchanged(keep)
    assert not own_temp.exists()
    res = registration.load(out)
    assert res.n_frames == 5 and all(res.status(k) == "ok" for k in range(5))
    assert (
        not (out / "frames" / "000005.json").exists()
        and not (out / "frames" / "000005.npz").exists()
    )
    rewritten = [p for p in old_records if p.exists() and p.suffix == ".json"]
    assert rewritten and all(snapshot(p)[p] != old_records[p] for p in rewritten)


def test_damaged_result_json_needs_force(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    (out / "result.json").write_bytes(b"\xff\xfe garbage")
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
    assert_refused(code, err, "register", "damaged registration result", "--force")
    assert_unchanged(before)
    code, _, err = cli(capsys, *register_args(sims[0], out), "--force")
    assert code == 0, err
    assert registration.load(out).records[3].status == "ok"


# ------------------------------------------------------------------------------------------
# register: frames that cannot be used fail alone


def test_corrupt_frame_fails_alone_and_the_run_goes_on(sims, tmp_path, capsys):
    frames = copy_frames(sims[0], tmp_path)
    truncate(frames / "000002.png")
    code, out_text, err = cli(capsys, *register_args(sims[0], tmp_path / "out", frames), "--json")
    assert code == 0, err
    summary = json.loads(out_text)
    assert summary["n_failed"] == 1 and summary["failed"][0]["frame"] == 2
    assert (
        "cannot read frame 2" in summary["failed"][0]["reason"]
        and "truncated PNG" in summary["failed"][0]["reason"]
    )
    res = registration.load(tmp_path / "out")
    truth = load_truth(sims[0])
    assert [res.records[k].status for k in range(N)] == ["ok", "ok", "failed", "ok", "ok", "ok"]
    # Frame 3 is registered against frame 1, the last good previous frame.
    assert truth_error(res, truth, 3) < 2.0


def test_frame_of_another_size_fails_naming_both_sizes(sims, tmp_path, capsys):
    frames = copy_frames(sims[0], tmp_path)
    img = cv2.imread(str(frames / "000003.png"))
    cv2.imwrite(str(frames / "000003.png"), cv2.resize(img, (400, 300)))
    code, _, err = cli(capsys, *register_args(sims[0], tmp_path / "out", frames))
    assert code == 0, err
    res = registration.load(tmp_path / "out")
    assert res.records[3].status == "failed"
    assert "frame 3 is 400x300 pixels but the reference frame is 480x360" in res.records[3].reason
    assert np.isnan(res.frame_to_base(3, [[100.0, 100.0]])).all()
    truth = load_truth(sims[0])
    assert truth_error(res, truth, 4) < 2.0 and truth_error(res, truth, 5) < 2.0


def test_frame_over_the_pixel_limit_fails_before_decoding(sims, tmp_path, capsys):
    frames = copy_frames(sims[0], tmp_path)
    png_header_only(frames / "000004.png", 20000, 20000)
    code, _, err = cli(capsys, *register_args(sims[0], tmp_path / "out", frames))
    assert code == 0, err
    rec = registration.load(tmp_path / "out").records[4]
    assert (
        rec.status == "failed"
        and "20000x20000 pixels (400 MP) is over the limit of 100 MP" in rec.reason
    )


@pytest.mark.parametrize(
    "damage, needle",
    [
        (lambda p: truncate(p), "truncated PNG"),
        (
            lambda p: cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (400, 300))),
            "400x300 pixels but the sequence's first readable frame is 480x360",
        ),
    ],
    ids=["truncated", "other-size"],
)
def test_unusable_reference_frame_is_refused_before_anything_is_written(
    sims, tmp_path, capsys, damage, needle
):
    frames = copy_frames(sims[0], tmp_path)
    damage(frames / "000001.png")
    code, _, err = cli(
        capsys, *register_args(sims[0], tmp_path / "out", frames), "--reference-frame", "1"
    )
    assert_refused(
        code, err, "register", "reference frame 1", needle, "choose another --reference-frame"
    )
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------
# damaged records


def test_damaged_records_are_reported_and_redone_by_resume(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    fr = out / "frames"
    flipped = bytearray((fr / "000001.npz").read_bytes())
    flipped[300:400] = bytes(b ^ 0x55 for b in flipped[300:400])
    (fr / "000001.npz").write_bytes(bytes(flipped))  # same size, corrupt inside
    truncate(fr / "000002.npz")
    (fr / "000003.npz").unlink()
    truncate(fr / "000004.json")
    untouched = snapshot(fr / "000000.json", fr / "000005.json", fr / "000005.npz")

    code, out_text, err = cli(capsys, "evaluate", out, "--truth", sims[0], "--json")
    assert code == 0 and "Traceback" not in err, err
    status = {p["frame"]: p["status"] for p in json.loads(out_text)["per_frame"]}
    assert status == {0: "ok", 1: "damaged", 2: "damaged", 3: "damaged", 4: "damaged", 5: "ok"}
    code, out_text, err = cli(capsys, "evaluate", out, "--truth", sims[0])
    assert code == 0 and "damaged record" in out_text and "1, 2, 3, 4" in out_text

    res = registration.load(out)
    # Missing or short files are seen at once; corruption inside the arrays when they are read.
    assert [res.status(k) for k in range(N)] == ["ok", "ok", "damaged", "damaged", "damaged", "ok"]
    assert np.isnan(res.frame_to_base(1, [[100.0, 100.0]], stage="local")).all()
    assert res.status(1) == "damaged" and "000001.npz" in res.records[1].reason

    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
    assert code == 0, err
    assert_unchanged(untouched)  # only the damaged frames were redone
    res = registration.load(out)
    assert all(res.status(k) == "ok" for k in range(N))
    truth = load_truth(sims[0])
    assert max(truth_error(res, truth, k) for k in range(N)) < 2.0


def test_missing_mid_base_image_redoes_the_reference_frame(sims, registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    (out / "mid_base.png").unlink()
    code, _, err = cli(capsys, *register_args(sims[0], out), "--resume")
    assert code == 0, err
    assert read_image(out / "mid_base.png").shape[:2] == read_image(sims[0] / "base.png").shape[:2]


# ------------------------------------------------------------------------------------------
# register: inputs and options at the boundary


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--gamma", "nan"], "--gamma must be a finite number"),
        (["--gamma", "abc"], "--gamma must be a number or 'auto', got 'abc'"),
        (["--seed", "1,2,3"], "--seed must be four numbers"),
        (["--seed", "nan,10,10,10"], "--seed must be four finite numbers, got 'nan,10,10,10'"),
        (["--seed", "10,10,-5,10"], "seed base point (-5.0, 10.0) lies outside"),
        (["--reference-frame", "99"], "reference frame 99 out of range: the sequence has 6 frames"),
        (["--reference-frame", "-1"], "reference frame -1 out of range"),
        (["--preset", "fastest"], "unknown preset 'fastest'"),
    ],
    ids=lambda v: "_".join(v) if isinstance(v, list) else None,
)
def test_register_bad_options(sims, tmp_path, capsys, extra, needle):
    out = tmp_path / "out"
    code, _, err = cli(capsys, *register_args(sims[0], out), *extra)
    assert_refused(code, err, "register", needle)
    assert not out.exists()


def test_register_gamma_outside_the_harris_range(sims, tmp_path, capsys):
    code, _, err = cli(capsys, *register_args(sims[0], tmp_path / "out"), "--gamma", "-50")
    assert_refused(code, err, "register", "gamma -50")
    assert not (tmp_path / "out").exists()


def test_export_reads_the_frames_it_registered_or_refuses(sims, tmp_path, capsys, monkeypatch):
    """A result registered from a relative path, exported from another folder holding another
    sequence at that relative path, renders its own frames (the path is stored absolute); when
    its own frames were replaced by another sequence's, export refuses in one line and writes
    nothing (it used to render the other flight, exit 0)."""
    here, there = tmp_path / "here", tmp_path / "there"
    for folder, sim in ((here, sims[0]), (there, sims[1])):
        shutil.copytree(sim / "frames", folder / "frames")
    shutil.copy(sims[0] / "base.png", here / "base.png")
    monkeypatch.chdir(here)
    argv = [
        "register",
        "--base",
        "base.png",
        "--frames",
        "frames",
        "--out",
        "reg",
        "--gamma",
        "0.7",
    ]
    assert cli(capsys, *argv)[0] == 0
    result = here / "reg"
    monkeypatch.chdir(there)
    code, _, err = cli(capsys, "export", result, "--format", "png", "--to", there / "png")
    assert code == 0, err
    own = read_image(there / "png" / "png" / "000002.png")
    # The result's own frames replaced by the other sequence's (same names, sizes and count).
    shutil.rmtree(here / "frames")
    shutil.copytree(sims[1] / "frames", here / "frames")
    before = snapshot(here, there)
    code, _, err = cli(capsys, "export", result, "--format", "png", "--to", there / "png2")
    assert_refused(
        code, err, "export", "are not the ones this result was registered from", "frame 0"
    )
    assert_unchanged(before)
    assert not (there / "png2").exists() or not any((there / "png2").iterdir())
    assert own.std() > 0


def test_a_failed_frame_is_a_hole_in_every_export_and_stale_files_go(sims, tmp_path, capsys):
    """Frame 2 truncated after a first export, the sequence registered again (--force): the
    export skips frame 2 (never reading it), writes everything else, says so, and with --force
    removes the 000002 files the first export wrote; the user's own files stay."""
    frames = tmp_path / "frames"
    shutil.copytree(sims[0] / "frames", frames)
    reg, ex = tmp_path / "reg", tmp_path / "ex"
    assert cli(capsys, *register_args(sims[0], reg, frames))[0] == 0
    formats = "png,transforms,mp4"  # a plain base map: no map formats
    code, _, err = cli(capsys, "export", reg, "--format", formats, "--to", ex)
    assert code == 0, err
    assert (ex / "png" / "000002.png").is_file()
    data = (frames / "000002.png").read_bytes()
    (frames / "000002.png").write_bytes(data[: len(data) // 2])
    code, out, err = cli(capsys, *register_args(sims[0], reg, frames), "--force")
    assert code == 0 and "frame 2 failed" in out, (out, err)
    mine = [ex / "png" / "notes.txt", ex / "png" / "000002.png.bak", ex / "000002.png"]
    mine.append(ex / "png" / ".notes.abcd1234.tmp")  # a temporary name, but not of an export file
    for p in mine:
        p.write_text("the user's")
    killed = ex / "png" / ".000004.png.k2x9_a7q.tmp"  # what a killed export leaves
    killed.write_bytes(b"half")
    before = snapshot(*mine)
    code, out, err = cli(capsys, "export", reg, "--format", formats, "--to", ex, "--force")
    assert code == 0, err
    assert "1 frame(s) failed in the registration and are left out: 2" in out
    # Frame 2's PNG and its world file (a plain base's own pixel grid), and the killed export's
    # temporary file.
    assert "removed 3 stale file(s) of an earlier export" in out
    assert not (ex / "png" / "000002.png").exists() and not killed.exists()
    assert not (ex / "png" / "000002.pgw").exists()
    for k in (0, 1, 3, 4, 5):
        assert (ex / "png" / f"{k:06d}.png").is_file()
    assert (ex / "registered.mp4").stat().st_size > 0 and (ex / "transforms.json").is_file()
    assert_unchanged(before)


def test_no_output_goes_into_the_inputs_or_the_records(sims, registered, tmp_path, capsys):
    """export --to the frames folder (it added mosaic.tif to the inputs) and evaluate --csv onto
    a record or an input frame (with --force it overwrote them) are refused in one line, and
    nothing changes."""
    out = copy_result(registered, tmp_path)
    frames = sims[0] / "frames"
    before = snapshot(out, frames)
    code, _, err = cli(capsys, "export", out, "--format", "png", "--to", frames)
    assert_refused(code, err, "export", "the export folder", "holds the run's inputs")
    code, _, err = cli(capsys, "export", out, "--format", "png", "--to", out / "frames" / "x")
    assert_refused(code, err, "export", "the export folder", "holds the run's inputs or records")
    for target in (out / "frames" / "000001.json", frames / "000002.png", out / "result.json"):
        code, _, err = cli(capsys, "evaluate", out, "--truth", sims[0], "--csv", target, "--force")
        assert_refused(code, err, "evaluate", "--csv")
    assert_unchanged(before)
    # Beside the records, in the result folder, is where exports go by default.
    code, _, err = cli(capsys, "export", out, "--format", "png")
    assert code == 0, err


def test_resume_with_another_base_nodata_is_refused(sims, tmp_path, capsys):
    """--base-nodata decides which map pixels control points may use: a resume with another
    one would mix two registrations (it was accepted, up to 11.9 px off either run)."""
    base = read_image(sims[0] / "base.png")
    base[40:120, 40:200] = 77  # a grey block: no-data only when --base-nodata 77 says so
    cv2.imwrite(str(tmp_path / "base.png"), base)
    out = tmp_path / "out"
    args = [*register_args(sims[0], out), "--base", tmp_path / "base.png"]
    assert cli(capsys, *args)[0] == 0
    before = snapshot(out)
    code, _, err = cli(capsys, *args, "--base-nodata", "77", "--resume")
    assert_refused(code, err, "register", "another no-data mask (--base-nodata)")
    assert_unchanged(before)
    assert cli(capsys, *args, "--resume")[0] == 0  # the same mask resumes


def test_a_wrong_click_leaves_no_result_behind(sims, tmp_path, capsys):
    """A run refused at the reference frame (a click 60 px off) computed nothing: it leaves no
    folder, and the run with the corrected click needs no --force."""
    truth = load_truth(sims[0])
    w, h = truth.frame_size
    bx, by = truth.frame_to_base(0, [[w / 2, h / 2]])[0]
    out = tmp_path / "reg"
    code, _, err = cli(
        capsys, *register_args(sims[0], out), "--seed", f"{w / 2},{h / 2},{bx - 9},{by - 60}"
    )
    assert_refused(code, err, "register", "check the click")
    assert not out.exists()
    # Into a folder the user made (and keeps other files in): only the run's own files go.
    out.mkdir()
    code, _, err = cli(
        capsys, *register_args(sims[0], out), "--seed", f"{w / 2},{h / 2},{bx - 9},{by - 60}"
    )
    assert_refused(code, err, "register", "check the click")
    assert out.is_dir() and not (out / "result.json").exists() and not (out / "frames").exists()
    code, _, err = cli(capsys, *register_args(sims[0], out), "--seed", f"{w / 2},{h / 2},{bx},{by}")
    assert code == 0, err


def test_gamma_auto_refuses_an_estimate_it_cannot_trust(sims, tmp_path, capsys):
    """A motionless flight cannot show the lens (the estimate runs to the end of its range):
    one line saying how to give γ, no result."""
    frames = tmp_path / "still"
    frames.mkdir()
    for k in range(4):
        shutil.copy(sims[0] / "frames" / "000000.png", frames / f"{k:06d}.png")
    out = tmp_path / "reg"
    args = [a for a in register_args(sims[0], out, frames) if a not in ("--gamma", "0.7")]
    code, _, err = cli(capsys, *args)  # the default is --gamma auto
    line = assert_refused(code, err, "register", "gamma could not be estimated", "--gamma G")
    assert "end of the searched range" in line
    assert not out.exists()


def make_bad_image(kind: str, folder: Path, source: Path) -> Path:
    """A bad image file of ``kind`` in ``folder`` (``source``: a good image to damage)."""
    path = folder / f"{kind}.png"
    if kind == "huge":
        return png_header_only(path, 20000, 20000)
    if kind in ("tiny", "one-pixel"):
        side = 8 if kind == "tiny" else 1
        cv2.imwrite(str(path), np.zeros((side, side, 3), np.uint8))
    elif kind == "truncated-jpeg":
        path = path.with_suffix(".jpg")
        cv2.imwrite(str(path), read_image(source))
        truncate(path)
    elif kind == "truncated-png":
        shutil.copy(source, path)
        truncate(path)
    elif kind == "crc":
        data = bytearray(source.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    elif kind == "text":
        path.write_text("not an image\n")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "directory":
        path.mkdir()
    elif kind != "missing":
        raise ValueError(kind)
    return path


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("huge", "20000x20000 pixels (400 MP) is over the limit of 250 MP"),
        ("tiny", "8x8 pixels is too small (at least 16 a side)"),
        ("truncated-jpeg", "truncated JPEG (no end-of-image marker)"),
        ("truncated-png", "truncated PNG (no IEND chunk"),
        ("crc", "corrupt PNG (chunk 'IDAT'"),
        ("text", "cannot read"),
        ("empty", "is empty"),
        ("directory", "is a directory"),
        ("missing", "image not found"),
    ],
)
def test_register_bad_base_map(sims, tmp_path, capsys, kind, needle):
    base = make_bad_image(kind, tmp_path, sims[0] / "base.png")
    out = tmp_path / "out"
    code, _, err = cli(
        capsys,
        "register",
        "--base",
        base,
        "--frames",
        sims[0] / "frames",
        "--out",
        out,
        "--gamma",
        "0.7",
    )
    assert_refused(code, err, "register", needle, str(base))
    assert not out.exists()


@pytest.mark.parametrize("suffix", [".tif", ".png"])
def test_a_base_map_too_large_for_the_memory_is_refused_before_reading(
    sims, tmp_path, capsys, monkeypatch, suffix
):
    """A compressed base map declaring 6000x6000 pixels (a GeoTIFF of blank tiles read through
    GDAL, a PNG through OpenCV), with 100 MB available: refused from its header in one line
    naming its size and the memory, before a pixel is read."""
    import rasterio
    from rasterio.transform import from_origin

    from registration.io import images

    base = tmp_path / f"big{suffix}"
    if suffix == ".tif":
        with rasterio.open(
            base, "w", driver="GTiff", width=6000, height=6000, count=3, dtype="uint8",
            crs="EPSG:32633", transform=from_origin(500000, 4000000, 0.1, 0.1),
            compress="deflate", tiled=True,
        ):  # fmt: skip
            pass
    else:
        cv2.imwrite(str(base), np.zeros((6000, 6000, 3), np.uint8))
    assert base.stat().st_size < 2_000_000
    monkeypatch.setattr(images, "available_memory_bytes", lambda: 100 << 20)
    read = []
    monkeypatch.setattr(images.cv2, "imdecode", lambda *a: read.append(1))
    out = tmp_path / "out"
    code, _, err = cli(
        capsys, "register", "--base", base, "--frames", sims[0] / "frames", "--out", out,
        "--gamma", "0.7",
    )  # fmt: skip
    per_px = images.GDAL_READ_BYTES_PER_PIXEL if suffix == ".tif" else images.DECODE_BYTES_PER_PIXEL
    needle = (
        f"reading its 6000x6000 pixels needs about {36e6 * per_px / 2**30:.1f} GiB of memory "
        "and 0.1 GiB is available: crop or downsample it first"
    )
    assert_refused(code, err, "register", needle, str(base))
    assert not read and not out.exists()


def test_a_blank_base_map_is_refused_before_it_is_read_whole(tmp_path, monkeypatch):
    """A GeoTIFF declaring 6000x6000 blank pixels (under 2 MB) is refused as all no-data from a
    scan of its windows, before it is read whole (measured on a 15000x15000 one: 0.11 GB and
    0.8 s CPU, where reading it whole took 5.84 GB and 14.6 s); one whose only data sits in its
    last window is read."""
    import rasterio
    from rasterio.transform import from_origin

    from registration.gis import basemap

    def tif(path, data=None):
        with rasterio.open(
            path, "w", driver="GTiff", width=6000, height=6000, count=3, dtype="uint8",
            crs="EPSG:32633", transform=from_origin(500000, 4000000, 0.1, 0.1),
            compress="deflate", tiled=True,
        ) as ds:  # fmt: skip
            if data is not None:
                ds.write(data, window=rasterio.windows.Window(5900, 5900, 100, 100))
        return path

    whole = []
    real = basemap._bands_to_bgr
    monkeypatch.setattr(basemap, "_bands_to_bgr", lambda *a: whole.append(1) or real(*a))
    with pytest.raises(ValueError, match=r"base map blank.tif has no valid pixels \(all no-data\)"):
        basemap.read_base_map(tif(tmp_path / "blank.tif"))
    assert not whole
    patch = np.full((3, 100, 100), 200, np.uint8)
    base = basemap.read_base_map(tif(tmp_path / "corner.tif", patch))
    assert whole and base.valid[5950, 5950] and (base.image[5950, 5950] == 200).all()


def make_bad_frames(kind: str, folder: Path) -> Path:
    if kind == "missing":
        return folder / "nothing"
    if kind == "glob":
        return folder / "*.nothing.png"
    if kind == "no-images":
        (folder / "docs").mkdir()
        (folder / "docs" / "a.txt").write_text("x")
        return folder / "docs"
    if kind == "fake-video":
        (folder / "clip.mp4").write_text("not a video")
        return folder / "clip.mp4"
    (folder / "huge").mkdir()
    png_header_only(folder / "huge" / "000000.png", 20000, 20000)
    return folder / "huge"


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("missing", "frames not found"),
        ("glob", "glob pattern matched no images"),
        ("no-images", "no images"),
        ("fake-video", "not a readable video"),
        ("only-huge", "no readable frame"),
    ],
)
def test_register_bad_frame_source(sims, tmp_path, capsys, kind, needle):
    frames = make_bad_frames(kind, tmp_path)
    out = tmp_path / "out"
    code, _, err = cli(
        capsys,
        "register",
        "--base",
        sims[0] / "base.png",
        "--frames",
        frames,
        "--out",
        out,
        "--gamma",
        "0.7",
    )
    assert_refused(code, err, "register", needle)
    assert not out.exists()


# ------------------------------------------------------------------------------------------
# evaluate


@pytest.mark.parametrize("kind", ["corrupt-result-json", "not-a-result", "missing"])
def test_evaluate_bad_result_folder(sims, registered, tmp_path, capsys, kind):
    if kind == "corrupt-result-json":
        folder, needle = copy_result(registered, tmp_path), "corrupt result.json"
        meta = json.loads((folder / "result.json").read_text())
        del meta["gamma"]
        (folder / "result.json").write_text(json.dumps(meta))
    else:
        folder = sims[0] if kind == "not-a-result" else tmp_path / "missing"
        needle = "no result.json"
    before = snapshot(folder) if folder.exists() else {}
    code, _, err = cli(capsys, "evaluate", folder, "--truth", sims[0])
    assert_refused(code, err, "evaluate", needle)
    assert_unchanged(before)


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("points-not-utf8", "is not UTF-8 text"),
        ("points-directory", "is a directory"),
        ("points-too-large", "over the 8 MiB limit"),
        ("truth-of-another-sequence", "the truth does not match the result"),
        ("grid-step-nan", "--grid-step must be a number >= 1"),
        ("grid-step-tiny", "--grid-step must be a number >= 1"),
        ("frames-for-table-0", "--frames-for-table must be >= 1"),
        ("truth-and-points", "exactly one of"),
    ],
)
def test_evaluate_bad_option(sims, registered, tmp_path, capsys, kind, needle):
    nonutf8 = tmp_path / "points.csv"
    nonutf8.write_bytes(b"point,frame,x,y\n\xff\xfe,0,1,2\n")
    extra = {
        "points-not-utf8": ["--points", nonutf8],
        "points-directory": ["--points", tmp_path],
        "points-too-large": ["--points", sparse_file(tmp_path / "big.csv", 9 << 20)],
        "truth-of-another-sequence": ["--truth", sims[1]],
        "grid-step-nan": ["--truth", sims[0], "--grid-step", "nan"],
        "grid-step-tiny": ["--truth", sims[0], "--grid-step", "0.001"],
        "frames-for-table-0": ["--truth", sims[0], "--frames-for-table", "0"],
        "truth-and-points": ["--truth", sims[0], "--points", nonutf8],
    }[kind]
    before = snapshot(registered, tmp_path)
    code, _, err = cli(capsys, "evaluate", registered, *extra)
    assert_refused(code, err, "evaluate", needle)
    assert_unchanged(before, no_new_under=tmp_path)


def test_evaluate_does_not_overwrite_without_force(sims, registered, tmp_path, capsys):
    report = tmp_path / "report.md"
    report.write_text("my notes\n")
    before = snapshot(report)
    code, _, err = cli(capsys, "evaluate", registered, "--truth", sims[0], "--markdown", report)
    assert_refused(code, err, "evaluate", f"--markdown {report} exists; pass --force")
    assert_unchanged(before)
    code, _, err = cli(
        capsys, "evaluate", registered, "--truth", sims[0], "--markdown", report, "--force"
    )
    assert code == 0, err
    assert "Post-Local" in report.read_text()


def test_evaluate_never_writes_over_its_inputs(sims, registered, tmp_path, capsys):
    before = snapshot(registered)
    code, _, err = cli(
        capsys, "evaluate", registered, "--truth", sims[0], "--csv", registered / "result.json",
        "--force",
    )  # fmt: skip
    assert_refused(code, err, "evaluate", "is an input of this command")
    assert_unchanged(before)


# ------------------------------------------------------------------------------------------
# undistort and calibrate


@pytest.fixture
def frame_png(sims) -> Path:
    return sims[0] / "frames" / "000000.png"


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("truncated-jpeg", "truncated JPEG"),
        ("huge", "over the limit of 100 MP"),
        ("one-pixel", "1x1 pixels is too small"),
        ("crc", "fails its CRC check"),
    ],
)
def test_undistort_bad_image(frame_png, tmp_path, capsys, kind, needle):
    image = make_bad_image(kind, tmp_path, frame_png)
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "undistort", image, "--gamma", "0.5", "-o", tmp_path / "u.png")
    assert_refused(code, err, "undistort", needle)
    assert_unchanged(before, no_new_under=tmp_path)


def test_undistort_gamma_nan(frame_png, tmp_path, capsys):
    code, _, err = cli(capsys, "undistort", frame_png, "--gamma", "nan", "-o", tmp_path / "u.png")
    assert_refused(code, err, "undistort", "gamma")
    assert not (tmp_path / "u.png").exists()


def test_undistort_gamma_far_out_of_range(frame_png, tmp_path, capsys):
    code, _, err = cli(capsys, "undistort", frame_png, "--gamma", "-50", "-o", tmp_path / "u.png")
    assert_refused(code, err, "undistort", "-50")
    assert not (tmp_path / "u.png").exists()


def test_undistort_onto_its_own_input(frame_png, tmp_path, capsys):
    image = tmp_path / "x.png"
    shutil.copy(frame_png, image)
    before = snapshot(image)
    code, _, err = cli(capsys, "undistort", image, "--gamma", "0.5", "-o", image)
    assert_refused(code, err, "undistort")
    assert_unchanged(before)


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("lines-not-utf8", "not valid JSON"),
        ("lines-too-large", "LINES.json files may be at most 8 MB"),
        ("lines-directory", "is a directory"),
        ("gamma-range-nan", "--gamma-range"),
        ("gamma-range-one-number", "--gamma-range must look like"),
        ("one-pixel-image", "1x1 pixels is too small"),
        ("missing-image", "image not found"),
        ("no-image", "give a raw IMAGE, or the flight's frames with --frames"),
        ("image-and-frames", "give IMAGE or --frames, not both"),
        ("frames-and-lines", "--lines is for one IMAGE"),
        ("frames-and-centre", "--center 'auto' is for straight lines"),
        ("frames-zero-pairs", "--pairs must be >= 1, got 0"),
        ("frames-step-zero", "--step must be >= 1, got 0"),
        ("frames-one-frame", "has 1 frame; γ from motion needs 2 or more"),
        ("frames-missing", "frames not found"),
    ],
)
def test_calibrate_bad_input(frame_png, tmp_path, capsys, kind, needle):
    inputs = tmp_path / "in"
    inputs.mkdir()
    nonutf8 = inputs / "nonutf8.json"
    nonutf8.write_bytes(b'\xff\xfe{"lines": \xff}')
    argv = {
        "lines-not-utf8": [frame_png, "--lines", nonutf8],
        "lines-too-large": [frame_png, "--lines", sparse_file(inputs / "LINES.json", 65 << 20)],
        "lines-directory": [frame_png, "--lines", inputs],
        "gamma-range-nan": [frame_png, "--gamma-range", "nan,1"],
        "gamma-range-one-number": [frame_png, "--gamma-range", "1"],
        "one-pixel-image": [make_bad_image("one-pixel", inputs, frame_png)],
        "missing-image": [inputs / "missing.png"],
        "no-image": [],
        "image-and-frames": [frame_png, "--frames", frame_png.parent],
        "frames-and-lines": ["--frames", frame_png.parent, "--lines", nonutf8],
        "frames-and-centre": ["--frames", frame_png.parent, "--center", "auto"],
        "frames-zero-pairs": ["--frames", frame_png.parent, "--pairs", "0"],
        "frames-step-zero": ["--frames", frame_png.parent, "--step", "0"],
        "frames-one-frame": ["--frames", frame_png],
        "frames-missing": ["--frames", inputs / "missing"],
    }[kind]
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "calibrate", *argv)
    assert_refused(code, err, "calibrate", needle)
    assert_unchanged(before, no_new_under=tmp_path)


def test_calibrate_degenerate_lines(frame_png, tmp_path, capsys):
    lines = tmp_path / "LINES.json"
    lines.write_text(
        json.dumps({"version": 1, "image_size": list(SIZE), "lines": [[[5, 5], [5, 5], [5, 5]]]})
    )
    code, _, err = cli(capsys, "calibrate", frame_png, "--lines", lines)
    assert_refused(code, err, "calibrate", "line")


# ------------------------------------------------------------------------------------------
# simulate


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--size", "100000x100000"], "at most 100 MP"),
        (["--size", "4x4"], "at least 16 pixels a side"),
        (["--size", "big"], "--size must look like 1280x960"),
        (["--frames", "0"], "frames"),
        (["--gamma", "nan"], "gamma"),
        (["--fps", "0"], "fps"),
    ],
    ids=lambda v: "_".join(v) if isinstance(v, list) else None,
)
def test_simulate_bad_option(tmp_path, capsys, extra, needle):
    code, _, err = cli(capsys, "simulate", tmp_path / "s", *extra)
    assert_refused(code, err, "simulate", needle)
    assert not (tmp_path / "s").exists()
    assert MAX_FRAME_PIXELS == 100_000_000


def test_simulate_out_that_is_a_file(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("keep\n")
    before = snapshot(afile)
    code, _, err = cli(capsys, "simulate", afile, "--frames", "2")
    assert_refused(code, err, "simulate", "not a folder")
    assert_unchanged(before)


def test_simulate_truncated_scene(frame_png, tmp_path, capsys):
    scene = make_bad_image("truncated-jpeg", tmp_path, frame_png)
    code, _, err = cli(
        capsys, "simulate", tmp_path / "s", "--scene", scene, "--frames", "2", "--no-video"
    )
    assert_refused(code, err, "simulate", "truncated JPEG")


def test_simulate_into_a_registration_result_changes_nothing(registered, tmp_path, capsys):
    out = copy_result(registered, tmp_path)
    before = snapshot(out)
    code, _, err = cli(capsys, "simulate", out, "--frames", "2", "--size", "320x240", "--no-video")
    assert_refused(code, err, "simulate")
    assert_unchanged(before)


# ------------------------------------------------------------------------------------------
# app command line (refused before any server starts; a case that is not would block until
# the timeout)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "kind, needle",
    [
        ("port", "--port must be 0..65535"),
        ("port-not-a-number", "invalid int value"),
        ("upload-nan", "--max-upload-mb must be a positive number"),
        ("upload-negative", "--max-upload-mb must be a positive number"),
        ("frames-without-base", "--frames and --base go together"),
        ("project-is-a-file", "is a file, not a folder"),
        ("allow-dir-missing", "--allow-dir is not a folder"),
        ("frames-missing", "--frames not found"),
    ],
)
def test_app_bad_option(sims, tmp_path, capsys, kind, needle):
    afile = tmp_path / "afile"
    afile.write_text("x")
    inputs = ["--frames", sims[0] / "frames", "--base", sims[0] / "base.png", "--port", "0"]
    extra = {
        "port": ["--port", "99999"],
        "port-not-a-number": ["--port", "x"],
        "upload-nan": [*inputs, "--max-upload-mb", "nan"],
        "upload-negative": [*inputs, "--max-upload-mb", "-1"],
        "frames-without-base": ["--frames", sims[0] / "frames"],
        "project-is-a-file": [*inputs, "--project", afile],
        "allow-dir-missing": [*inputs, "--allow-dir", tmp_path / "nope"],
        "frames-missing": ["--frames", tmp_path / "nope", "--base", sims[0] / "base.png"],
    }[kind]
    before = snapshot(tmp_path)
    code, _, err = cli(capsys, "app", *extra)
    assert_refused(code, err, "app", needle)
    assert_unchanged(before, no_new_under=tmp_path)


# ------------------------------------------------------------------------------------------
# bench


@pytest.mark.parametrize(
    "kind, needle",
    [
        ("unknown-suite", "unknown bench suite 'nosuch'"),
        ("frames-0", "--frames must be 1..1000"),
        ("size-1x1", "at least 16 pixels a side"),
        ("scene-missing", "image not found"),
        ("scene-without-base", "--scene and --base go together"),
        ("profile-unknown", "invalid choice: 'nosuch'"),
        ("profile-other-suite", "--profile goes with the suites register, scaleout, traffic only"),
        ("speed-options-other-suite", "--speed-options goes with the register suite only"),
    ],
)
def test_bench_bad_option(tmp_path, capsys, kind, needle):
    missing = tmp_path / "no.png"
    argv = {
        "unknown-suite": ["nosuch"],
        "frames-0": ["register", "--frames", "0"],
        "size-1x1": ["register", "--size", "1x1"],
        "scene-missing": ["register", "--scene", missing, "--base", missing],
        "scene-without-base": ["register", "--scene", missing],
        "profile-unknown": ["register", "--profile", "nosuch"],
        "profile-other-suite": ["register", "simulate", "--profile", "paper-hard"],
        "speed-options-other-suite": ["scaleout", "--speed-options"],
    }[kind]
    code, _, err = cli(capsys, "bench", *argv)
    assert_refused(code, err, "bench", needle)
    assert "running" not in err


# ------------------------------------------------------------------------------------------
# the app: a result of other inputs is not continued


@pytest.mark.timeout(300)
def test_app_register_all_after_opening_other_inputs_recomputes(sims, tmp_path):
    """Register A, open B (same shape) in the same project, "Register all frames": B's frames are
    registered, not A's result shown as B's (issue 12)."""
    viser = pytest.importorskip("viser")
    from app.gui.project import Project
    from app.gui.server import App

    a, b = sims
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(
        server,
        Project(tmp_path / "proj"),
        frames=str(a / "frames"),
        base=str(a / "base.png"),
        allowed_dirs=[tmp_path, a.parent],
    )
    app.start()
    try:
        app.worker.wait_idle()
        seq = app.views["Sequence"]
        assert seq.run()
        app.jobs.join(300)
        app.worker.wait_idle()
        result_dir = app.project.result_dir
        first = registration.load(result_dir)
        assert first.inputs_difference(open_frames(a / "frames"), read_image(a / "base.png")) == ""
        app.open_inputs(str(b / "frames"), str(b / "base.png"), client=None)
        app.worker.wait_idle()
        assert seq.run()
        app.jobs.join(300)
        app.worker.wait_idle()
        second = registration.load(result_dir)
        b_frames = open_frames(b / "frames")
        assert second.inputs_difference(b_frames, read_image(b / "base.png")) == ""
        assert "frame 0" in second.inputs_difference(
            open_frames(a / "frames"), read_image(a / "base.png")
        )
        hashes = {hashlib.sha256(p.read_bytes()).hexdigest() for p in (b / "frames").glob("*.png")}
        assert all(r.input_sha256 in hashes for r in second.records if r.status != "pending")
        assert "Starting a new result" in [n[0] for n in app.notices]
    finally:
        app.stop()


# ------------------------------------------------------------------------------------------
# image reading at the boundary (registration.io)


def _encodings(img: np.ndarray) -> dict[str, bytes]:
    from io import BytesIO

    from PIL import Image

    out = {
        ext: cv2.imencode(ext, img)[1].tobytes()
        for ext in (".png", ".jpg", ".tif", ".bmp", ".webp")
    }
    out[".jpg-progressive"] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[
        1
    ].tobytes()
    out[".png-16bit"] = cv2.imencode(".png", img.astype(np.uint16) * 257)[1].tobytes()
    out[".webp-lossless"] = cv2.imencode(".webp", img, [cv2.IMWRITE_WEBP_QUALITY, 101])[1].tobytes()
    for fmt, kw in (("TIFF", {"big_tiff": True}), ("JPEG", {"exif": Image.Exif()}), ("BMP", {})):
        buf = BytesIO()
        Image.fromarray(img[:, :, ::-1]).save(buf, fmt, **kw)
        out[f"pil-{fmt}-{'-'.join(kw) or 'plain'}"] = buf.getvalue()
    return out


def test_header_sizes_match_the_decoded_images():
    """The size read from the header (before decoding, for the limits) is the decoded size."""
    from registration.io import image_header_size, incomplete_image

    img = np.random.default_rng(0).integers(0, 255, (37, 53, 3), np.uint8)
    for name, data in _encodings(img).items():
        assert image_header_size(data) == (53, 37), name
        assert incomplete_image(data) == "", name
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert decoded.shape[:2] == (37, 53), name


@pytest.mark.parametrize("fmt", [".png", ".jpg", ".webp"])
def test_truncated_files_are_found_before_decoding(fmt):
    from registration.io import incomplete_image

    img = np.random.default_rng(1).integers(0, 255, (64, 80, 3), np.uint8)
    data = cv2.imencode(fmt, img)[1].tobytes()
    for cut in (0.3, 0.9, (len(data) - 2) / len(data)):
        assert incomplete_image(data[: int(len(data) * cut)]).startswith("truncated"), (fmt, cut)


def test_frame_read_errors_name_the_frame(sims, tmp_path):
    from registration.io import FrameReadError

    frames = copy_frames(sims[0], tmp_path)
    truncate(frames / "000003.png")
    src = open_frames(frames)
    assert src.size == SIZE
    with pytest.raises(FrameReadError, match=r"000003\.png: truncated PNG"):
        src.get(3)
    # The size comes from the first readable frame, here frame 1.
    truncate(frames / "000000.png")
    assert open_frames(frames).size == SIZE


# ------------------------------------------------------------------------------------------
# videos


def test_resume_with_another_video_is_refused_and_a_copied_one_accepted(sims, tmp_path, capsys):
    from registration.render import write_video

    videos = {}
    for name, sim in zip("AB", sims, strict=True):
        videos[name] = tmp_path / f"{name}.mp4"
        write_video(
            [read_image(p) for p in sorted((sim / "frames").glob("*.png"))], videos[name], fps=5
        )
    out = tmp_path / "out"
    assert cli(capsys, *register_args(sims[0], out, videos["A"]))[0] == 0
    before = snapshot(out)
    code, _, err = cli(capsys, *register_args(sims[0], out, videos["B"]), "--resume")
    assert_refused(code, err, "register", "the video B.mp4 differs from the run's input")
    assert_unchanged(before)
    copy = tmp_path / "copy" / "A.mp4"
    copy.parent.mkdir()
    shutil.copyfile(videos["A"], copy)  # same bytes, new mtime
    code, _, err = cli(capsys, *register_args(sims[0], out, copy), "--resume")
    assert code == 0, err
    assert_unchanged(before)
    # 64 bytes changed in the middle, size and mtime kept: the first and last 64 KB agree, the
    # decoded frames do not; the whole-file hash refuses it.
    data = bytearray(copy.read_bytes())
    stat = copy.stat()
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(255 - b for b in data[middle : middle + 64])
    copy.write_bytes(bytes(data))
    os.utime(copy, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert 64 * 1024 < middle < len(data) - 64 * 1024 - 64  # outside the sampled bytes
    code, _, err = cli(capsys, *register_args(sims[0], out, copy), "--resume")
    assert_refused(code, err, "register", "A.mp4 differs from the run's input", "content changed")
    assert_unchanged(before)
