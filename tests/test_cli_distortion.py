"""``aerialreg undistort`` and ``aerialreg calibrate``: results, JSON output and bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from app.cli import main
from registration.calibration import save_lines, straight_edge_chart
from registration.distortion import HarrisModel, simulate_raw_frame, undistort_image

W, H = 480, 360


@pytest.fixture(scope="module")
def raw_png(tmp_path_factory):
    """A raw 480x360 frame of the generated chart seen through a lens with γ = 0.6."""
    chart = straight_edge_chart(1000, 750, seed=2)
    raw, _ = simulate_raw_frame(chart, HarrisModel(0.6, W, H))
    path = tmp_path_factory.mktemp("img") / "raw.png"
    cv2.imwrite(str(path), cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR))
    return path


def lines_for(gamma, w=W, h=H):
    t = np.linspace(0, 1, 40)[:, None]
    segs = [
        ((10, 15), (470, 25)),
        ((20, 340), (460, 330)),
        ((12, 20), (25, 340)),
        ((200, 10), (210, 350)),
    ]
    model = HarrisModel(gamma, w, h)
    return [model.raw_from_corrected(np.array(a) + t * (np.subtract(b, a))) for a, b in segs]


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, cmd, *needles):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"aerialreg {cmd}: error: ")
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])


# ------------------------------------------------------------------------------------------
# undistort


@pytest.mark.parametrize("canvas", ["same", "full"])
def test_undistort_writes_the_corrected_image(raw_png, tmp_path, capsys, canvas):
    out = tmp_path / f"out_{canvas}.png"
    code, stdout, _ = run(
        capsys,
        "undistort",
        str(raw_png),
        "--gamma",
        "0.6",
        "-o",
        str(out),
        "--canvas",
        canvas,
        "--json",
    )
    assert code == 0
    report = json.loads(stdout)  # exactly one JSON object
    assert report["gamma"] == 0.6 and report["canvas"]["kind"] == canvas
    written = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    expected, info = undistort_image(
        cv2.imread(str(raw_png)), HarrisModel(0.6, W, H), canvas=canvas
    )
    np.testing.assert_array_equal(written, expected)
    assert report["canvas"]["width"] == info.width == written.shape[1]
    if canvas == "full":
        assert written.shape[1] > W and report["canvas"]["origin"][0] < 0


def test_undistort_keeps_grey_and_cubic(tmp_path, capsys):
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.tile(np.arange(W, dtype=np.uint8), (H, 1)))
    out = tmp_path / "o.png"
    code, _, err = run(
        capsys, "undistort", str(grey), "--gamma", "0.3", "-o", str(out), "--interpolation", "cubic"
    )
    assert code == 0 and "wrote" in err
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).shape == (H, W)


def test_undistort_bad_input(raw_png, tmp_path, capsys):
    out = str(tmp_path / "o.png")
    code, _, err = run(
        capsys, "undistort", str(tmp_path / "missing.png"), "--gamma", "0.5", "-o", out
    )
    assert_one_line_error(code, err, "undistort", "image not found", "missing.png")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    code, _, err = run(capsys, "undistort", str(empty), "--gamma", "0.5", "-o", out)
    assert_one_line_error(code, err, "undistort", "is empty")
    text = tmp_path / "notes.png"
    text.write_text("this is not an image\n")
    code, _, err = run(capsys, "undistort", str(text), "--gamma", "0.5", "-o", out)
    assert_one_line_error(code, err, "undistort", "cannot read", "as an image")
    code, _, err = run(capsys, "undistort", str(tmp_path), "--gamma", "0.5", "-o", out)
    assert_one_line_error(code, err, "undistort", "is a directory")
    code, _, err = run(capsys, "undistort", str(raw_png), "--gamma", "2.5", "-o", out)
    assert_one_line_error(
        code, err, "undistort", "gamma 2.5 is out of range for a 480x360 frame", "valid gamma <"
    )
    code, _, err = run(
        capsys, "undistort", str(raw_png), "--gamma", "0.5", "-o", str(tmp_path / "x.nope")
    )
    assert_one_line_error(code, err, "undistort", "cannot write images of type '.nope'")
    code, _, err = run(
        capsys,
        "undistort",
        str(raw_png),
        "--gamma",
        "0.5",
        "-o",
        str(tmp_path / "no" / "dir" / "o.png"),
    )
    assert_one_line_error(code, err, "undistort", "does not exist")
    code, _, err = run(
        capsys, "undistort", str(raw_png), "--gamma", "1.0", "-o", out, "--canvas", "full"
    )
    assert_one_line_error(code, err, "undistort", "full canvas")


# ------------------------------------------------------------------------------------------
# calibrate


def test_calibrate_from_lines_json(raw_png, tmp_path, capsys):
    lines = tmp_path / "LINES.json"
    save_lines(lines, lines_for(0.6), (W, H))
    code, stdout, _ = run(capsys, "calibrate", str(raw_png), "--lines", str(lines), "--json")
    assert code == 0
    d = json.loads(stdout)
    assert d["gamma"] == pytest.approx(0.6, abs=1e-3)
    assert d["method"] == "lines" and d["n_lines"] == 4 and "uncertainty" in d
    assert len(d["gamma_grid"]) == len(d["residual_curve"])
    code, stdout, err = run(capsys, "calibrate", str(raw_png), "--lines", str(lines))
    assert code == 0 and stdout.startswith("gamma 0.6") and "4 lines" in err


def test_calibrate_auto(raw_png, capsys):
    code, stdout, _ = run(capsys, "calibrate", str(raw_png), "--json")
    assert code == 0
    assert len(stdout.strip().splitlines()) == 1
    d = json.loads(stdout)
    assert d["gamma"] == pytest.approx(0.6, abs=0.02)
    assert d["method"] == "auto" and d["n_lines"] >= 5


def test_calibrate_bad_input(raw_png, tmp_path, capsys):
    code, _, err = run(capsys, "calibrate", str(tmp_path / "nope.jpg"))
    assert_one_line_error(code, err, "calibrate", "image not found")
    short = tmp_path / "short.json"
    short.write_text(
        json.dumps(
            {
                "version": 1,
                "image_size": [W, H],
                "lines": [[[1, 1], [5, 5], [9, 9]], [[3, 3], [4, 4]]],
            }
        )
    )
    code, _, err = run(capsys, "calibrate", str(raw_png), "--lines", str(short))
    assert_one_line_error(code, err, "calibrate", "lines[1] has 2 points", "at least 3")
    broken = tmp_path / "broken.json"
    broken.write_text('{"version": 1, "lines": [')
    code, _, err = run(capsys, "calibrate", str(raw_png), "--lines", str(broken))
    assert_one_line_error(code, err, "calibrate", "not valid JSON", "broken.json")
    other = tmp_path / "other.json"
    save_lines(other, lines_for(0.6, 640, 480), (640, 480))
    code, _, err = run(capsys, "calibrate", str(raw_png), "--lines", str(other))
    assert_one_line_error(code, err, "calibrate", "640x480 image but", "480x360")
    code, _, err = run(capsys, "calibrate", str(raw_png), "--lines", str(tmp_path / "none.json"))
    assert_one_line_error(code, err, "calibrate", "lines file not found")
    flat = tmp_path / "flat.png"
    cv2.imwrite(str(flat), np.full((H, W), 90, np.uint8))
    code, _, err = run(capsys, "calibrate", str(flat))
    assert_one_line_error(code, err, "calibrate", "found 0 long")
    code, _, err = run(capsys, "calibrate", str(raw_png), "--gamma-range", "0.5")
    assert_one_line_error(code, err, "calibrate", "--gamma-range must look like")


@pytest.mark.parametrize(
    "cmd,options",
    [
        ("undistort", ["--gamma", "--output", "--canvas", "--interpolation", "--json", "IMAGE"]),
        ("calibrate", ["--lines", "--gamma-range", "--json", "IMAGE"]),
    ],
)
def test_help_documents_every_option(cmd, options, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for opt in options:
        assert opt in text
