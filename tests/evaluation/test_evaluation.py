"""Evaluation (paper section 6): Table 2 by hand, truth mode on known mappings, points files,
sudden excursions, and the ``aerialreg evaluate`` command's errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.cli import main
from registration import evaluation
from registration.coords import as_points
from registration.evaluation import EvaluationConfig, Table2
from registration.run import FrameRecord

# --------------------------------------------------------------------------------------------
# Fakes with known mappings


class LookupResult:
    """A result whose frame_to_base returns hand-chosen base positions for hand-chosen raw
    points: ``table[stage][k][(x, y)] = (bx, by)``. gamma 0: corrected = raw."""

    gamma = 0.0
    frame_size = (100, 80)
    base_size = (500, 500)
    reference_frame = 0

    def __init__(self, table, n_frames=5):
        self.table = table
        self.n_frames = n_frames
        self.records = [FrameRecord("ok") for _ in range(n_frames)]

    def frame_to_base(self, k, xy, stage="local"):
        return np.array([self.table[stage][k][tuple(p)] for p in as_points(xy).tolist()], float)

    def base_to_frame(self, k, xy, stage="local"):  # pragma: no cover - not used here
        raise NotImplementedError


class ShiftTruth:
    """Frame k sees base point b at raw b - T[k], T[k] = (3k, 4k) (gamma 0, no distortion)."""

    gamma = 0.0
    frame_size = (200, 160)
    base_size = (400, 400)

    def __init__(self, n_frames=5):
        self.n_frames = n_frames

    def shift(self, k):
        return np.array([3.0 * k, 4.0 * k])

    def frame_to_base(self, k, xy, stage="local"):
        return as_points(xy) + self.shift(k)

    def base_to_frame(self, k, xy, stage="local"):
        return as_points(xy) - self.shift(k)


class OffsetResult:
    """Truth plus known errors: global +(0.5 + 0.1 k, 0) px in frame k, local +(0, 0.1) px;
    frame 3 failed."""

    reference_frame = 0

    def __init__(self, truth, failed=(3,)):
        self.truth = truth
        self.n_frames = truth.n_frames
        self.gamma = truth.gamma
        self.frame_size = truth.frame_size
        self.base_size = truth.base_size
        self.failed = set(failed)
        self.records = [
            FrameRecord("failed" if k in self.failed else "ok") for k in range(self.n_frames)
        ]

    def frame_to_base(self, k, xy, stage="local"):
        b = self.truth.frame_to_base(k, xy)
        if k in self.failed:
            return np.full_like(b, np.nan)
        return b + ([0.5 + 0.1 * k, 0.0] if stage == "global" else [0.0, 0.1])

    def base_to_frame(self, k, xy, stage="local"):  # pragma: no cover - not used here
        raise NotImplementedError


def write_points(tmp_path, text, name="points.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


POINTS = """# hand-marked ground points
point,frame,x,y
NW,0,10,10
NW,2,13,14
NW,4,16,18
SE,0,90,70
SE,2,90,70
SE,4,84,62
"""

# Registered positions (base px) of the marked points, chosen so that every motion is a
# round number (3-4-5 triangles).
TABLE = {
    "global": {
        0: {(10, 10): (200, 200), (90, 70): (300, 300)},
        2: {(13, 14): (201, 200), (90, 70): (300, 300)},
        4: {(16, 18): (200, 203), (84, 62): (304, 303)},
    },
    "local": {
        0: {(10, 10): (200, 200), (90, 70): (300, 300)},
        2: {(13, 14): (200, 200.5), (90, 70): (300, 300)},
        4: {(16, 18): (200, 201.5), (84, 62): (300.6, 300.8)},
    },
}


# --------------------------------------------------------------------------------------------
# Table 2


def test_table2_average_reproduces_the_paper():
    mu = {"unregistered": [86.7, 96.0, 69.0, 125.9, 88.8], "local": [1.7, 1.0, 0.9, 1.0, 0.8]}
    sd = {"unregistered": [46.0, 60.0, 49.2, 50.2, 46.2], "local": [1.0, 0.7, 0.6, 0.7, 0.3]}
    t = Table2(list(evaluation.LOCATIONS), mu, sd, {s: [10] * 5 for s in mu})
    am, asd = t.average("unregistered")
    assert am == pytest.approx(93.28) and asd == pytest.approx(50.32)
    md = t.to_markdown().splitlines()
    assert md[0] == "| Stage | NW | | NE | | Center | | SW | | SE | | Average | |"
    assert md[2] == "| |" + " μ | σ |" * 6
    assert (
        md[3]
        == "| Unregistered | 86.7 | 46.0 | 96.0 | 60.0 | 69.0 | 49.2 | 125.9 | 50.2 | 88.8 | 46.2 | 93.3 | 50.3 |"
    )
    assert md[4].startswith("| Post-Local | 1.7 | 1.0 |") and md[4].endswith("| 1.1 | 0.7 |")
    csv_lines = t.to_csv().splitlines()
    assert csv_lines[0].startswith("Stage,NW_mu,NW_sigma,NE_mu") and csv_lines[0].endswith(
        "Average_mu,Average_sigma"
    )
    assert csv_lines[1].split(",")[-2:] == ["93.280", "50.320"]


def test_table2_hand_made_points_reference_anchor(tmp_path):
    result = LookupResult(TABLE)
    marks = evaluation.read_points_csv(write_points(tmp_path, POINTS), 5, result.frame_size)
    assert marks.locations == ["NW", "SE"]
    rep = evaluation.evaluate_points(result, marks, EvaluationConfig())
    rows = rep.table.to_dict()["rows"]
    # Unregistered (corrected = raw, gamma 0), motions from frame 0: NW 5, 10; SE 0, 10.
    assert rows["unregistered"]["mu"] == pytest.approx([7.5, 5.0])
    assert rows["unregistered"]["sigma"] == pytest.approx([2.5, 5.0])
    assert rows["unregistered"]["average_mu"] == pytest.approx(6.25)
    assert rows["unregistered"]["average_sigma"] == pytest.approx(3.75)
    # Post-Global: NW 1, 3; SE 0, 5.
    assert rows["global"]["mu"] == pytest.approx([2.0, 2.5])
    assert rows["global"]["sigma"] == pytest.approx([1.0, 2.5])
    assert rows["global"]["average_mu"] == pytest.approx(2.25)
    # Post-Local: NW 0.5, 1.5; SE 0, 1.0.
    assert rows["local"]["mu"] == pytest.approx([1.0, 0.5])
    assert rows["local"]["sigma"] == pytest.approx([0.5, 0.5])
    assert rows["local"]["n"] == [2, 2]
    assert rep.table.frames == {"NW": [2, 4], "SE": [2, 4]}
    # Per frame: the mean over the points marked in it.
    pf = {p["frame"]: p for p in rep.per_frame}
    assert sorted(pf) == [2, 4]
    assert pf[4]["global"]["mean"] == pytest.approx(4.0)
    md = rep.table.to_markdown().splitlines()
    assert md[3] == "| Unregistered | 7.5 | 2.5 | 5.0 | 5.0 | 6.2 | 3.8 |"
    assert md[4] == "| Post-Global | 2.0 | 1.0 | 2.5 | 2.5 | 2.2 | 1.8 |"


def test_table2_hand_made_points_mean_anchor(tmp_path):
    result = LookupResult(TABLE)
    marks = evaluation.read_points_csv(write_points(tmp_path, POINTS), 5, result.frame_size)
    rep = evaluation.evaluate_points(result, marks, EvaluationConfig(anchor="mean"))
    rows = rep.table.to_dict()["rows"]
    # NW raw (10,10), (13,14), (16,18): mean (13,14), distances 5, 0, 5.
    assert rows["unregistered"]["mu"][0] == pytest.approx(10 / 3)
    assert rows["unregistered"]["sigma"][0] == pytest.approx(math.sqrt(50 / 9))
    assert rows["unregistered"]["n"] == [3, 3]


def test_points_need_the_reference_frame_with_reference_anchor(tmp_path):
    text = "point,frame,x,y\nNW,1,10,10\nNW,2,12,10\n"
    marks = evaluation.read_points_csv(write_points(tmp_path, text), 5, (100, 80))
    with pytest.raises(ValueError, match="not marked in the reference frame 0"):
        evaluation.evaluate_points(LookupResult(TABLE), marks, EvaluationConfig())


# --------------------------------------------------------------------------------------------
# Truth mode


def test_truth_mode_known_errors():
    truth = ShiftTruth(n_frames=5)
    result = OffsetResult(truth)
    rep = evaluation.evaluate_truth(
        result, truth, EvaluationConfig(grid_step_px=20.0, table_frames=3)
    )
    pf = {p["frame"]: p for p in rep.per_frame}
    for k in (0, 1, 2, 4):
        assert pf[k]["global"]["mean"] == pytest.approx(0.5 + 0.1 * k)
        assert pf[k]["global"]["max"] == pytest.approx(0.5 + 0.1 * k)
        assert pf[k]["local"]["p95"] == pytest.approx(0.1)
        assert pf[k]["n_points"] > 50
        if k:  # motion relative to the reference frame 0
            assert pf[k]["motion"]["global"]["mean"] == pytest.approx(0.1 * k)
            assert pf[k]["motion"]["local"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert pf[0]["motion"]["global"]["n"] == 0  # the reference frame is left out
    assert pf[3]["status"] == "failed" and pf[3]["global"]["n"] == 0
    # Unregistered: a ground point moves by T[0] - T[k] = 5k px between frames.
    assert pf[2]["unregistered"]["mean"] == pytest.approx(10.0)
    assert pf[0]["unregistered"]["n"] == 0
    assert rep.summary["local"]["mean"] == pytest.approx(0.1)
    assert rep.summary["global"]["mean_of_frame_means"] == pytest.approx(
        (0.5 + 0.6 + 0.7 + 0.9) / 4
    )
    assert rep.summary_motion["global"]["mean_of_frame_means"] == pytest.approx(
        (0.1 + 0.2 + 0.4) / 3
    )
    # Table 2 (motion) over frames 2, 4 (0 is the reference): unregistered 10, 20 px;
    # global 0.2, 0.4; local 0.
    rows = rep.table.to_dict()["rows"]
    assert rep.table.locations == list(evaluation.LOCATIONS)
    assert rows["unregistered"]["mu"] == pytest.approx([15.0] * 5)
    assert rows["unregistered"]["sigma"] == pytest.approx([5.0] * 5)
    assert rows["global"]["mu"] == pytest.approx([0.3] * 5)
    assert rows["global"]["sigma"] == pytest.approx([0.1] * 5)
    assert rows["local"]["average_mu"] == pytest.approx(0.0, abs=1e-9)
    # The same layout against the truth, frames 0, 2, 4: global 0.5, 0.7, 0.9; local 0.1.
    rows = rep.table_absolute.to_dict()["rows"]
    assert rows["global"]["mu"] == pytest.approx([0.7] * 5)
    assert rows["global"]["sigma"] == pytest.approx([math.sqrt(0.08 / 3)] * 5)
    assert rows["local"]["average_mu"] == pytest.approx(0.1)
    assert rows["unregistered"]["n"] == [2] * 5
    assert json.loads(json.dumps(rep.to_dict()))["mode"] == "truth"


@pytest.mark.parametrize(
    ("attr", "value", "message"),
    [
        ("n_frames", 7, "7 frames in the truth, 5 in the result"),
        ("frame_size", (320, 240), "frame size 320x240 in the truth, 200x160 in the result"),
        ("gamma", 0.7, "gamma 0.7 in the truth, 0 in the result"),
        ("base_size", (800, 800), "base size 800x800"),
    ],
)
def test_truth_result_mismatch_is_one_line(attr, value, message):
    truth = ShiftTruth(5)
    result = OffsetResult(ShiftTruth(5))
    setattr(truth, attr, value)
    with pytest.raises(ValueError, match=message) as exc:
        evaluation.evaluate_truth(result, truth)
    assert "\n" not in str(exc.value)


def test_a_result_with_an_estimated_gamma_is_evaluated():
    """A γ up to 0.05 off the truth's (an estimate: calibrate, register --gamma auto) is the same
    sequence, evaluated like the exact one (the result maps its raw pixels through its own γ;
    only the unregistered motion, in corrected px, follows the γ); further off is another
    simulation, refused."""
    truth = ShiftTruth(5)
    exact = evaluation.evaluate_truth(OffsetResult(ShiftTruth(5)), truth)
    near = OffsetResult(ShiftTruth(5))
    near.gamma = truth.gamma + 0.03
    estimated = evaluation.evaluate_truth(near, truth)
    rows, exact_rows = (r.table_absolute.to_dict()["rows"] for r in (estimated, exact))
    assert rows["global"] == exact_rows["global"] and rows["local"] == exact_rows["local"]
    near.gamma = truth.gamma + 0.06
    with pytest.raises(ValueError, match=r"gamma 0 in the truth, 0.06 in the result \(an"):
        evaluation.evaluate_truth(near, truth)


def test_table_frames_spread_evenly():
    assert evaluation.table_frames(100, 10) == [0, 11, 22, 33, 44, 55, 66, 77, 88, 99]
    assert evaluation.table_frames(4, 10) == [0, 1, 2, 3]


# --------------------------------------------------------------------------------------------
# Excursions


def test_excursions_flag_the_jump_only():
    errors = [1.0 + 0.05 * ((k * 7) % 5) for k in range(20)]
    errors[7] = 4.0
    errors[13] = 1.6  # a jump, but below the 1 px floor
    errors[16] = math.nan  # a failed frame is skipped
    exc = evaluation.find_excursions(range(20), errors, EvaluationConfig())
    assert [e["frame"] for e in exc] == [7]
    assert exc[0]["excess"] > 2.5
    # A steady drift is not an excursion.
    assert evaluation.find_excursions(range(20), [0.1 * k for k in range(20)]) == []


# --------------------------------------------------------------------------------------------
# Points files: bad input -> one line naming the problem and the value


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("NW,0,1,2\nNW,1,1,2\n", "line 1: missing header 'point,frame,x,y'"),
        ("point,frame,x\nNW,0,1\n", "header lacks column 'y'"),
        ("point,frame,x,y\nNW,0,1,2\nNW,abc,1,2\n", "line 3: frame must be an integer, got 'abc'"),
        ("point,frame,x,y\nNW,0,1\n", "line 2: expected 4 fields"),
        ("point,frame,x,y\nNW,0,nan,2\n", "line 2: x must be a finite number, got 'nan'"),
        (
            "point,frame,x,y\nNW,0,1,2\nNW,7,1,2\n",
            "line 3: frame 7 is not in the result \\(frames 0..4\\)",
        ),
        (
            "point,frame,x,y\nNW,0,1,2\nNW,1,1,2\nSE,0,5,5\n",
            "point 'SE' is marked in 1 frame\\(s\\) \\(0\\)",
        ),
        ("point,frame,x,y\nNW,0,1,2\nNW,0,3,4\n", "line 3: point 'NW' is marked twice in frame 0"),
        (
            "point,frame,x,y\nNW,0,1,2\nNW,1,150,2\n",
            "line 3: \\(150, 2\\) lies outside the 100x80 raw frame",
        ),
        ("point,frame,x,y\n", "has a header but no points"),
        ("", "is empty"),
    ],
)
def test_bad_points_files(tmp_path, text, message):
    with pytest.raises(ValueError, match=message) as exc:
        evaluation.read_points_csv(write_points(tmp_path, text), 5, (100, 80))
    assert "\n" not in str(exc.value)


def test_points_file_extra_columns_and_order(tmp_path):
    text = "x,y,frame,point,note\n1,2,0,Tower,roof corner\n3,4,1,Tower,\n5,6,0,A,\n7,8,2,A,\n"
    marks = evaluation.read_points_csv(write_points(tmp_path, text), 5, (100, 80))
    assert marks.locations == ["Tower", "A"]
    assert marks.marks["Tower"] == {0: (1.0, 2.0), 1: (3.0, 4.0)}


# --------------------------------------------------------------------------------------------
# The command, on a hand-written result folder (translation models, gamma 0)


def make_result_folder(tmp_path, n_frames=5):
    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    meta = {
        "format": "aerialreg-result",
        "version": 1,
        "n_frames": n_frames,
        "gamma": 0.0,
        "frame_size": [100, 80],
        "base_size": [500, 500],
        "reference_frame": 0,
        "config": {},
    }
    (out / "result.json").write_text(json.dumps(meta))
    for k in range(n_frames):
        # Frame k sees the ground shifted by (1.5k, 2k): the model undoes it.
        model = {"type": "Translation", "params": [-1.5 * k, -2.0 * k]}
        rec = {"status": "ok", "reason": "", "stats": {}, "model": model}
        (out / "frames" / f"{k:06d}.json").write_text(json.dumps(rec))
    return out


CLI_POINTS = "point,frame,x,y\nNW,0,10,10\nNW,2,13,14\nNW,4,16.6,18.8\nSE,0,90,70\nSE,4,96,78\n"


def test_cli_points_table(tmp_path, capsys):
    out = make_result_folder(tmp_path)
    pts = write_points(tmp_path, CLI_POINTS)
    md, csv_path = tmp_path / "t2.md", tmp_path / "t2.csv"
    rc = main(
        [
            "evaluate",
            str(out),
            "--points",
            str(pts),
            "--json",
            "--markdown",
            str(md),
            "--csv",
            str(csv_path),
        ]
    )
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    data = json.loads(captured.out)
    rows = data["table2"]["rows"]
    assert data["table2"]["locations"] == ["NW", "SE"]
    # Unregistered: NW (3,4) -> 5, (6.6,8.8) -> 11; SE (6,8) -> 10.
    # Registered (model undoes (1.5k, 2k)): NW 0, (0.6,0.8) -> 1; SE 0.
    assert rows["unregistered"]["mu"] == pytest.approx([8.0, 10.0])
    assert rows["unregistered"]["sigma"] == pytest.approx([3.0, 0.0])
    assert rows["global"]["mu"] == pytest.approx([0.5, 0.0])
    assert rows["global"]["sigma"] == pytest.approx([0.5, 0.0])
    assert rows["local"]["mu"] == pytest.approx([0.5, 0.0])  # no field: local = global
    assert "| Post-Global | 0.5 | 0.5 | 0.0 | 0.0 |" in md.read_text()
    assert (
        csv_path.read_text().splitlines()[0]
        == "Stage,NW_mu,NW_sigma,SE_mu,SE_sigma,Average_mu,Average_sigma"
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("point,frame,x,y\nNW,0,1,2\nNW,9,1,2\n", "frame 9 is not in the result (frames 0..4)"),
        ("point,frame,x,y\nNW,0,1,2\n", "point 'NW' is marked in 1 frame(s)"),
        ("point,frame,x,y\nNW,0,1,2\nNW;1;1;2\n", "line 3: expected 4 fields"),
        ("NW,0,1,2\n", "missing header"),
    ],
)
def test_cli_bad_points_one_line_exit_2(tmp_path, capsys, text, message):
    out = make_result_folder(tmp_path)
    rc = main(["evaluate", str(out), "--points", str(write_points(tmp_path, text))])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("aerialreg evaluate: error: ")
    assert message in err


def test_cli_truth_mismatch_one_line_exit_2(tmp_path, capsys, monkeypatch):
    import registration.synth

    out = make_result_folder(tmp_path, n_frames=5)
    truth = ShiftTruth(n_frames=8)
    truth.frame_size = (100, 80)
    monkeypatch.setattr(registration.synth, "load_truth", lambda d: truth)
    rc = main(["evaluate", str(out), "--truth", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "8 frames in the truth, 5 in the result" in err


def test_cli_needs_exactly_one_source(tmp_path, capsys):
    out = make_result_folder(tmp_path)
    assert main(["evaluate", str(out)]) == 2
    assert "exactly one of --truth DIR or --points" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "nope"), "--points", "x.csv"]) == 2
    assert "no result.json" in capsys.readouterr().err


def test_points_mode_equals_truth_mode_for_exact_marks():
    """Marks placed exactly where the truth puts the five ground points give the truth mode's
    Table 2 (both measure motion relative to the reference frame)."""
    truth = ShiftTruth(n_frames=5)
    result = OffsetResult(truth, failed=())
    config = EvaluationConfig(table_frames=5)
    b = truth.frame_to_base(0, evaluation.table_points(truth.frame_size, config.table_inset))
    marks = {
        loc: {k: tuple(truth.base_to_frame(k, b[i : i + 1])[0]) for k in range(5)}
        for i, loc in enumerate(evaluation.LOCATIONS)
    }
    pm = evaluation.PointMarks(marks, list(evaluation.LOCATIONS))
    t_points = evaluation.evaluate_points(result, pm, config).table.to_dict()
    t_truth = evaluation.evaluate_truth(result, truth, config).table.to_dict()
    for s in evaluation.STAGES:
        assert t_points["rows"][s]["mu"] == pytest.approx(t_truth["rows"][s]["mu"])
        assert t_points["rows"][s]["sigma"] == pytest.approx(t_truth["rows"][s]["sigma"], abs=1e-12)


class TurningTruth:
    """Frame k turned by 7k degrees, scaled by 1 + 0.03 k and shifted (40k, 25k) over the base
    (gamma 0): frames see different ground, so a table's points depend on the frame chosen."""

    gamma = 0.0
    frame_size = (200, 160)
    base_size = (800, 800)

    def __init__(self, n_frames=6):
        self.n_frames = n_frames

    def _affine(self, k):
        a = np.deg2rad(7.0 * k)
        s = 1.0 + 0.03 * k
        m = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return m, np.array([200.0 + 40.0 * k, 150.0 + 25.0 * k])

    def frame_to_base(self, k, xy, stage="local"):
        m, t = self._affine(k)
        return as_points(xy) @ m.T + t

    def base_to_frame(self, k, xy, stage="local"):
        m, t = self._affine(k)
        return (as_points(xy) - t) @ np.linalg.inv(m).T


class FieldErrorResult(OffsetResult):
    """The truth with an error that varies over the base: frame k's positions moved by
    ``t_k + A_k (b - 400)``; reference frame 2."""

    reference_frame = 2

    def __init__(self, truth):
        super().__init__(truth, failed=())
        rng = np.random.default_rng(11)
        self.t = rng.uniform(-1, 1, (truth.n_frames, 2))
        self.a = rng.uniform(-0.01, 0.01, (truth.n_frames, 2, 2))

    def error(self, k, b):
        return self.t[k] + (b - 400.0) @ self.a[k].T

    def frame_to_base(self, k, xy, stage="local"):
        b = self.truth.frame_to_base(k, xy)
        return b + self.error(k, b)


def test_truth_table2_takes_its_points_from_the_reference_frame():
    """Table 2's five ground points are the reference frame's (frame 2 here), not frame 0's:
    computed independently from the known error field, each location's motion matches."""
    truth = TurningTruth()
    result = FieldErrorResult(truth)
    config = EvaluationConfig(table_frames=6)
    report = evaluation.evaluate_truth(result, truth, config)
    ref = result.reference_frame
    b = truth.frame_to_base(ref, evaluation.table_points(truth.frame_size, config.table_inset))
    b0 = truth.frame_to_base(0, evaluation.table_points(truth.frame_size, config.table_inset))
    assert np.abs(b - b0).max() > 50  # frame 0's points are elsewhere
    for i in range(len(evaluation.LOCATIONS)):
        motion = [
            float(np.hypot(*(result.error(k, b[i]) - result.error(ref, b[i]))))
            for k in range(truth.n_frames)
            if k != ref
        ]
        assert report.table.mu["local"][i] == pytest.approx(np.mean(motion), abs=1e-9)
        assert report.table.sigma["local"][i] == pytest.approx(np.std(motion), abs=1e-9)


def test_a_points_file_too_large_to_be_hand_marks_is_refused_before_reading(tmp_path):
    from registration.evaluation.points import MAX_POINTS_FILE_BYTES

    p = tmp_path / "POINTS.csv"
    with open(p, "w") as f:
        f.write("point,frame,x,y\n")
        f.truncate(MAX_POINTS_FILE_BYTES + 1)  # sparse: nothing to parse, only its size
    with pytest.raises(ValueError, match=r"points file .*POINTS\.csv has 8\.0 MiB, over the 8 MiB"):
        evaluation.read_points_csv(p, 10, (640, 480))
