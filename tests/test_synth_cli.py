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
    rc = main(["simulate", str(tmp_path / "o"), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err[-1].startswith("aerialreg simulate: error: ") and needle in err[-1]


def test_simulate_cli_demo_flags(tmp_path, capsys):
    assert main(["simulate", "--demo", str(tmp_path)]) == 2
    assert "--demo takes no OUT" in capsys.readouterr().err
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
