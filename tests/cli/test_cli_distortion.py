"""``aerialreg undistort`` and ``aerialreg calibrate``: results, JSON output and bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from app.cli import main
from registration.lens import (
    HarrisModel,
    save_lines,
    simulate_raw_frame,
    straight_edge_chart,
    undistort_image,
)

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
        code, err, "undistort", "gamma 2.5 is out of range for a 480x360 frame", "valid -1 <="
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
    assert d["center"] == [239.5, 179.5] and d["center_source"] == "frame"
    assert isinstance(d["confident"], bool) and d["evidence"]
    assert d["model_check"]["enough"] is True
    assert not d["center_fit"]["supported"]
    assert len(d["gamma_grid"]) == len(d["residual_curve"])
    code, stdout, err = run(capsys, "calibrate", str(raw_png), "--lines", str(lines))
    assert code == 0 and stdout.startswith("gamma 0.6") and "4 lines" in err
    assert "centre (239.5, 179.5) [frame]" in err and "one parameter is enough" in err


def test_calibrate_auto(raw_png, capsys):
    code, stdout, _ = run(capsys, "calibrate", str(raw_png), "--json")
    assert code == 0
    assert len(stdout.strip().splitlines()) == 1
    d = json.loads(stdout)
    assert d["gamma"] == pytest.approx(0.6, abs=0.02)
    assert d["method"] == "auto" and d["n_lines"] >= 5
    assert abs(d["gamma"] - 0.6) <= 2 * d["uncertainty"]
    for key in ("confident", "evidence", "center", "center_source", "center_fit", "model_check"):
        assert key in d


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
        (
            "undistort",
            ["--gamma", "--output", "--center", "--canvas", "--interpolation", "--json", "IMAGE"],
        ),
        ("calibrate", ["--lines", "--gamma-range", "--center", "--json", "IMAGE"]),
    ],
)
def test_help_documents_every_option(cmd, options, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for opt in options:
        assert opt in text


# ------------------------------------------------------------------------------------------
# a distortion centre off the frame centre


def test_calibrate_center_auto_finds_an_off_centre_lens(tmp_path, capsys):
    c = (239.5 + 30.0, 179.5 - 18.0)
    model = HarrisModel(0.6, W, H, center=c)
    rng = np.random.default_rng(4)
    lines = []
    while len(lines) < 20:
        a = rng.uniform([0.05, 0.05], [0.95, 0.95]) * [W - 1, H - 1]
        ang = rng.uniform(0, np.pi)
        pts = a + np.linspace(-1, 1, 40)[:, None] * [np.cos(ang), np.sin(ang)] * 200
        ok = (pts[:, 0] > 3) & (pts[:, 0] < W - 4) & (pts[:, 1] > 3) & (pts[:, 1] < H - 4)
        if ok.sum() >= 15:
            lines.append(model.raw_from_corrected(pts[ok]) + rng.normal(0, 0.1, (ok.sum(), 2)))
    path = tmp_path / "L.json"
    save_lines(path, lines, (W, H))
    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.full((H, W), 90, np.uint8))
    code, stdout, _ = run(capsys, "calibrate", str(img), "--lines", str(path), "--json")
    d = json.loads(stdout)
    assert code == 0 and d["center_source"] == "frame" and d["center_fit"]["supported"]
    code, stdout, err = run(
        capsys, "calibrate", str(img), "--lines", str(path), "--center", "auto", "--json"
    )
    d = json.loads(stdout)
    assert code == 0 and d["center_source"] == "estimated"
    assert d["center"] == pytest.approx(c, abs=2.0)
    assert d["gamma"] == pytest.approx(0.6, abs=0.01)
    # The same centre given explicitly.
    code, stdout, _ = run(
        capsys, "calibrate", str(img), "--lines", str(path), "--center", f"{c[0]},{c[1]}", "--json"
    )
    d = json.loads(stdout)
    assert d["center_source"] == "given" and d["center"] == [c[0], c[1]]


def test_undistort_with_a_given_centre(raw_png, tmp_path, capsys):
    out = tmp_path / "c.png"
    code, stdout, _ = run(
        capsys,
        "undistort",
        str(raw_png),
        "--gamma",
        "0.6",
        "--center",
        "200,150",
        "-o",
        str(out),
        "--json",
    )
    assert code == 0 and json.loads(stdout)["center"] == [200.0, 150.0]
    expected, _ = undistort_image(
        cv2.imread(str(raw_png)), HarrisModel(0.6, W, H, center=(200.0, 150.0))
    )
    np.testing.assert_array_equal(cv2.imread(str(out), cv2.IMREAD_UNCHANGED), expected)


# ------------------------------------------------------------------------------------------
# bad input: one line, exit 2, no traceback, nothing already there changed


def snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def refused(capsys, folder, cmd, argv, *needles):
    """Run, assert a one-line error naming ``needles`` and that no file in ``folder`` changed
    or appeared."""
    before = snapshot(folder)
    code, out, err = run(capsys, cmd, *argv)
    assert_one_line_error(code, err, cmd, *needles)
    assert out == ""
    assert snapshot(folder) == before
    return err


@pytest.fixture
def workdir(tmp_path, raw_png):
    """A folder with an image and an existing output that a refused command must not touch."""
    img = tmp_path / "x.png"
    img.write_bytes(raw_png.read_bytes())
    (tmp_path / "out.png").write_bytes(b"previous result")
    return tmp_path


def test_one_pixel_image_is_refused(workdir, capsys):
    tiny = workdir / "tiny.png"
    cv2.imwrite(str(tiny), np.full((1, 1), 200, np.uint8))
    out = str(workdir / "out.png")
    refused(
        capsys,
        workdir,
        "undistort",
        [str(tiny), "--gamma", "0.5", "-o", out],
        "1x1 pixels is too small",
        "at least 16 a side",
    )
    refused(capsys, workdir, "calibrate", [str(tiny)], "1x1 pixels", "at least 16 a side")
    refused(capsys, workdir, "calibrate", [str(tiny), "--json"], "1x1 pixels")


def test_image_size_limits_at_the_boundary(workdir, capsys, monkeypatch):
    import registration.io as rio

    out = workdir / "out.png"
    small = workdir / "s16.png"
    cv2.imwrite(str(small), np.full((16, 16), 100, np.uint8))
    code, _, _ = run(
        capsys, "undistort", str(small), "--gamma", "0.3", "-o", str(workdir / "ok.png")
    )
    assert code == 0  # exactly the minimum
    too_small = workdir / "s15.png"
    cv2.imwrite(str(too_small), np.full((16, 15), 100, np.uint8))
    refused(
        capsys,
        workdir,
        "undistort",
        [str(too_small), "--gamma", "0.3", "-o", str(out)],
        "15x16 pixels",
    )
    monkeypatch.setattr(rio, "MAX_FRAME_PIXELS", 400)
    at = workdir / "m20.png"
    cv2.imwrite(str(at), np.full((20, 20), 100, np.uint8))
    code, _, _ = run(capsys, "undistort", str(at), "--gamma", "0.3", "-o", str(workdir / "ok2.png"))
    assert code == 0  # exactly the maximum
    over = workdir / "m21.png"
    cv2.imwrite(str(over), np.full((20, 21), 100, np.uint8))
    refused(
        capsys,
        workdir,
        "undistort",
        [str(over), "--gamma", "0.3", "-o", str(out)],
        "21x20 pixels",
        "over the limit",
    )
    refused(capsys, workdir, "calibrate", [str(over)], "21x20 pixels", "over the limit")


def test_gamma_outside_the_valid_range_is_refused(workdir, capsys):
    img, out = str(workdir / "x.png"), str(workdir / "out.png")
    for g in ("-50", "-1.01", "1.5"):
        refused(
            capsys,
            workdir,
            "undistort",
            [img, "--gamma", g, "-o", out],
            f"gamma {float(g):g} is out of range",
            "valid -1 <= gamma < 1.0046",
        )
    code, _, _ = run(capsys, "undistort", img, "--gamma", "-1", "-o", str(workdir / "ok.png"))
    assert code == 0  # the end of the range is allowed
    refused(capsys, workdir, "undistort", [img, "--gamma", "nan", "-o", out], "out of range")
    refused(capsys, workdir, "calibrate", [img, "--gamma-range=-5,1"], "starts below -1")


def test_undistort_refuses_to_overwrite_its_input(workdir, capsys):
    img = workdir / "x.png"
    refused(
        capsys,
        workdir,
        "undistort",
        [str(img), "--gamma", "0.3", "-o", str(img)],
        "is the input image",
    )
    # Also through another spelling of the same path.
    other = workdir / "sub"
    other.mkdir()
    refused(
        capsys,
        workdir,
        "undistort",
        [str(img), "--gamma", "0.3", "-o", str(other / ".." / "x.png")],
        "is the input image",
    )


def test_degenerate_lines_json_is_refused(workdir, capsys):
    path = workdir / "same.json"
    path.write_text(
        json.dumps(
            {
                "version": 1,
                "image_size": [W, H],
                "lines": [[[10, 10]] * 5, [[1, 1], [100, 2], [200, 4]]],
            }
        )
    )
    refused(
        capsys,
        workdir,
        "calibrate",
        [str(workdir / "x.png"), "--lines", str(path), "--json"],
        "lines[0] is degenerate",
        "within 1 px of (10, 10)",
    )


def test_lines_json_size_limits(workdir, capsys, monkeypatch):
    from registration.lens import lines_file

    img = str(workdir / "x.png")
    good = workdir / "good.json"
    save_lines(good, lines_for(0.6), (W, H))
    size = good.stat().st_size
    monkeypatch.setattr(lines_file, "MAX_LINES_FILE_BYTES", size)
    code, _, _ = run(capsys, "calibrate", img, "--lines", str(good))
    assert code == 0  # exactly at the limit
    big = workdir / "big.json"
    big.write_bytes(good.read_bytes() + b" ")
    refused(
        capsys,
        workdir,
        "calibrate",
        [img, "--lines", str(big)],
        f"file is {(size + 1) / 1e6:.1f} MB",
        "at most",
    )
    monkeypatch.setattr(lines_file, "MAX_LINES_FILE_BYTES", 10**7)
    monkeypatch.setattr(lines_file, "MAX_LINES", 3)
    refused(capsys, workdir, "calibrate", [img, "--lines", str(good)], "4 lines; at most 3")
    monkeypatch.setattr(lines_file, "MAX_LINES", 100)
    monkeypatch.setattr(lines_file, "MAX_LINES_POINTS", 159)
    refused(
        capsys, workdir, "calibrate", [img, "--lines", str(good)], "160 points in all; at most 159"
    )
