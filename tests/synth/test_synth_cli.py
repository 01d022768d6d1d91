"""``aerialreg simulate``: outputs, --json, and one-line errors with exit status 2."""

from __future__ import annotations

import json

import pytest

from app.cli import main


def test_simulate_cli_writes_sequence(tmp_path, capsys):
    out = tmp_path / "sim"
    rc = main(
        [
            "simulate",
            str(out),
            "--frames",
            "2",
            "--size",
            "160x120",
            "--seed",
            "3",
            "--json",
            "--no-vehicles",
        ]
    )
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_frames"] == 2 and info["frame_size"] == [160, 120]
    assert info["config"]["vehicles"] is False
    for rel in ("frames/000000.png", "frames/000001.png", "base.png", "truth.json", "sequence.mp4"):
        assert (out / rel).is_file(), rel


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--size", "0x240"], "--size must be positive"),
        (["--size", "abc"], "--size must look like"),
        (["--gamma", "1.5"], "gamma must be in the valid Harris range"),
        (["--frames", "-1"], "number of frames must be positive"),
        (["--rolling-shutter", "0.5"], "rolling shutter"),
        (["--base", "x.png"], "--base needs --scene"),
        (["--scene", "/nonexistent/scene.png"], "--scene image not found"),
        (["--scale", "50"], "frame scale"),
    ],
)
def test_simulate_cli_errors(tmp_path, capsys, argv, needle):
    try:
        rc = main(["simulate", str(tmp_path / "o"), *argv])
    except SystemExit as exc:  # argparse's own errors (bad types) exit from the parser
        rc = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1, err  # one line: no usage, no progress bar, no traceback
    assert err[0].startswith("aerialreg simulate: error: ") and needle in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--size", "9000x100"], "between 16 and 8192 px per side, got 9000x100"),
        (["--size", "8000x8000"], "8000x8000 is 64.0 MP, over the limit of 40 MP"),
        (["--frames", "200000"], "at most 100000, got 200000"),
        (["--frames", "3000", "--size", "2560x1920"], "14.7 gigapixels, over the limit of 10"),
        (["--frames", "abc"], "argument --frames: invalid int value: 'abc'"),
        (["--profile", "nope"], "unknown profile 'nope'; choose from default, paper-hard"),
        (["--base-heading", "nan"], "base heading must be a finite angle"),
        (["--base-scale", "0.01"], "base scale must be in [0.05, 8]"),
        (["--seed", "-3"], "seed must be a non-negative integer, got -3"),
        (["--lens-k2", "0.3"], "gamma + lens_k2 must be at most 0.9"),
        (["--vehicle-gap", "-1"], "vehicle_gap_m must be in [0, 100] m, got -1.0"),
        (["--vehicle-headway", "1"], "vehicle_headway_s (1.0) needs vehicle_gap_m"),
        (["--shake", "0.01", "--size", "64x48"], "shake_deg 0.01 is below"),
        (["--profile", "paper-hard", "--frames", "3"], "use more frames (paper-hard needs ~15)"),
        (["--fps", "nan"], "fps must be positive"),
        (["--rebase", "/nonexistent", "--base-heading", "30"], "--rebase source folder not found"),
        (["--rebase", "x", "--frames", "3"], "--rebase reuses SRC's frames"),
        (["--rebase", "x"], "--rebase needs --base-heading and/or --base-scale"),
        (["--scene", "s.png", "--base-from-scene", "1,0,0,0,1"], "needs 9 finite numbers"),
        (["--scene", "s.png", "--base-from-scene", "1", "0", "x"], "needs 9 numbers, got '1 0 x'"),
    ],
)
def test_simulate_cli_limits_one_line(tmp_path, capsys, argv, needle):
    test_simulate_cli_errors(tmp_path, capsys, argv, needle)


def test_simulate_cli_force_profile_and_rebase(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = ["simulate", str(out), "--profile", "paper-hard", "--size", "160x120", "--frames", "16"]
    assert main([*argv, "--no-video", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    cfg = info["config"]
    # Profile values, with the command line's overrides.
    assert info["profile"] == "paper-hard" and cfg["n_frames"] == 16
    assert cfg["rolling_shutter_s"] == 0.15 and cfg["lens_k2"] == 0.04 and cfg["shake_deg"] == 0.6
    assert cfg["unregistered_px"] == pytest.approx(93.3 * 160 / 2560)
    assert cfg["vehicle_gap_m"] is None  # vehicles at their own speeds unless asked
    first = (out / "frames" / "000000.png").read_bytes()
    # Again without --force: refused in one line, nothing touched.
    assert main([*argv, "--seed", "5", "--no-video"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds a simulated sequence" in err[0] and str(out) in err[0]
    assert (out / "frames" / "000000.png").read_bytes() == first
    assert main([*argv, "--seed", "5", "--no-video", "--force"]) == 0
    capsys.readouterr()
    assert (out / "frames" / "000000.png").read_bytes() != first
    # A copy with the base turned and halved.
    rot = tmp_path / "rot"
    assert main(["simulate", str(rot), "--rebase", str(out), "--base-heading", "30",
                 "--base-scale", "0.5", "--json"]) == 0  # fmt: skip
    info = json.loads(capsys.readouterr().out)
    assert info["base_heading_deg"] == 30.0 and info["base_scale"] == 0.5
    assert (rot / "frames" / "000000.png").samefile(out / "frames" / "000000.png")


def test_simulate_cli_foreign_folder(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine")
    argv = ["simulate", str(tmp_path), "--size", "64x48", "--frames", "2", "--no-video"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not empty and is not a simulator output" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    assert main([*argv, "--force"]) == 0
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_simulate_cli_demo_flags(tmp_path, capsys):
    assert main(["simulate", "--demo", str(tmp_path)]) == 2
    assert "--demo takes no OUT" in capsys.readouterr().err
    assert main(["simulate", "--demo", "--profile", "paper-hard"]) == 2
    assert "got --profile" in capsys.readouterr().err
    assert main(["simulate"]) == 2
    assert "OUT is required" in capsys.readouterr().err


def test_simulate_cli_demo_uses_cache(tmp_path, capsys, monkeypatch):
    from registration.synth import SimConfig
    from registration.synth import demo as demomod

    monkeypatch.setenv("AERIALREG_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(
        demomod, "DEMO_CONFIG", SimConfig(frame_size=(160, 120), n_frames=2, seed=1)
    )
    assert main(["simulate", "--demo", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["out"] == str((tmp_path / "demo-v1").resolve())


def test_simulate_cli_base_from_scene_in_exponent_notation(tmp_path, capsys):
    """A homography estimated from images has tiny perspective terms such as -8.5e-07, which
    argparse takes for an option when given as separate arguments: one comma-separated value
    after ``=`` passes it, and the truth carries it exactly."""
    import cv2
    import numpy as np

    from registration.synth import load_truth

    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.integers(0, 256, (300, 400, 3), dtype=np.uint8), (5, 5), 1.5)
    cv2.imwrite(str(tmp_path / "scene.png"), scene)
    h = [1.01, 0.02, -5.5, -0.03, 0.99, 4.25, -8.5e-07, 3.25e-06, 1.0]
    rc = main(
        [
            "simulate", str(tmp_path / "sim"), "--scene", str(tmp_path / "scene.png"),
            "--base-from-scene=" + ",".join(repr(v) for v in h), "--frames", "2",
            "--size", "160x120", "--no-video",
        ]
    )  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    truth = load_truth(tmp_path / "sim")
    np.testing.assert_allclose(truth.geometry.base_from_scene, np.reshape(h, (3, 3)), rtol=1e-12)


def test_simulate_cli_refuses_a_scene_too_small_for_the_flight(tmp_path, capsys):
    """A flight whose frames would sample the scene finer than its pixels (a long flight over a
    small photo) is refused in one line instead of rendering upsampled, textureless frames;
    ``--scale`` forces it."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.integers(0, 256, (300, 400, 3), dtype=np.uint8), (5, 5), 1.5)
    cv2.imwrite(str(tmp_path / "scene.png"), scene)
    argv = ["simulate", str(tmp_path / "o"), "--scene", str(tmp_path / "scene.png"),
            "--size", "320x240", "--frames", "3", "--no-video"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "upsampled" in err[0] and "scene px" in err[0], err
    assert main([*argv, "--scale", "0.5", "--force"]) == 0


def test_simulate_cli_vehicle_gap_reaches_the_flight(tmp_path, capsys):
    from registration.synth import load_truth

    out = tmp_path / "sim"
    argv = ["simulate", str(out), "--size", "160x120", "--frames", "2", "--vehicle-gap", "2.5"]
    assert main([*argv, "--no-video", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["config"]["vehicle_gap_m"] == 2.5
    assert load_truth(out).config["vehicle_gap_m"] == 2.5
    out = tmp_path / "sim_headway"
    argv = ["simulate", str(out), "--size", "160x120", "--frames", "2", "--vehicle-gap", "2"]
    assert main([*argv, "--vehicle-headway", "1.5", "--no-video", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["config"]["vehicle_headway_s"] == 1.5
    assert load_truth(out).config["vehicle_headway_s"] == 1.5
