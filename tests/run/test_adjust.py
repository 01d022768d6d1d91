"""The sequence adjustment in a registration run (``PipelineConfig.adjust``), against the
simulator's exact truth: consecutive frames agree better at the global stage, no frame moves
away from the truth, the local stage and each frame's own model are kept, the records say what
was adjusted and how well, and an interrupted adjustment resumes to the same bits."""

from __future__ import annotations

import json
import shutil
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

import registration
from app.cli import main as cli_main
from registration.adjustment import SequenceAdjustConfig
from registration.evaluation import evaluate_truth
from registration.run import get_preset, load_config
from registration.synth import load_truth
from tests.conftest import SIM_SEQUENCE, seed_for
from tests.conftest import register as run

N_FRAMES = SIM_SEQUENCE["n_frames"]
# Windows of 4 frames, 2 final each: the 6 frames take two windows.
SMALL = SequenceAdjustConfig(window_frames=4, final_frames=2, link_steps=(1, 2))


def _config(adjust=SMALL):
    return replace(get_preset("default"), adjust=adjust)


@pytest.fixture(scope="module")
def adjusted(sim_seq, tmp_path_factory):
    return run(sim_seq, tmp_path_factory.mktemp("adjusted") / "out", config=_config())


def _grid(truth, n=9, margin=0.1):
    w, h = truth.frame_size
    gx, gy = np.meshgrid(
        np.linspace(margin * w, (1 - margin) * w, n), np.linspace(margin * h, (1 - margin) * h, n)
    )
    return np.c_[gx.ravel(), gy.ravel()]


def _map_error(result, truth, k, stage="global"):
    g = _grid(truth)
    return float(
        np.mean(np.hypot(*(result.frame_to_base(k, g, stage) - truth.frame_to_base(k, g)).T))
    )


def _pair_error(result, truth, k, stage="global"):
    """90th percentile over ground points seen in frames k and k+1 of the difference between
    the two frames' registration errors there (what a speed from the two frames suffers)."""
    g = _grid(truth, 15, 0.05)
    b = truth.frame_to_base(k, g)
    q = truth.base_to_frame(k + 1, b)
    w, h = truth.frame_size
    inside = np.isfinite(q).all(1) & (q[:, 0] > 0) & (q[:, 0] < w) & (q[:, 1] > 0) & (q[:, 1] < h)
    d = result.frame_to_base(k, g[inside], stage) - result.frame_to_base(k + 1, q[inside], stage)
    return float(np.percentile(np.hypot(*d.T), 90))


def test_adjusted_frames_agree_with_each_other_and_the_truth(sim_seq, default_result, adjusted):
    truth = load_truth(sim_seq)
    own = default_result.unadjusted()
    pairs_own = [_pair_error(own, truth, k) for k in range(N_FRAMES - 1)]
    pairs_adj = [_pair_error(adjusted, truth, k) for k in range(N_FRAMES - 1)]
    # Measured 0.54 -> 0.41 px (the rest is relief, which no global model of a frame follows).
    assert np.mean(pairs_adj) < 0.85 * np.mean(pairs_own), (pairs_own, pairs_adj)
    for k in range(N_FRAMES):
        e_own, e_adj = _map_error(own, truth, k), _map_error(adjusted, truth, k)
        assert e_adj < e_own + 0.02, f"frame {k}: {e_own:.3f} -> {e_adj:.3f} px from the truth"
    # Each frame keeps its own model; the reference frame is held.
    for k in range(N_FRAMES):
        assert adjusted.records[k].model == own.records[k].model
        assert adjusted.is_adjusted(k)
    assert adjusted.records[0].adjusted_model == adjusted.records[0].model


def test_the_local_stage_on_the_adjusted_models_keeps_its_accuracy(
    sim_seq, default_result, adjusted
):
    """The simulated frames' own local stages agree with each other to within their links'
    noise (within 0.1 px of the truth, where the links are 0.2-0.6 px from it): the links do not
    move them (within a few hundredths of a px), and no frame, nor any pair of consecutive
    frames, moves away from the truth."""
    truth = load_truth(sim_seq)
    g = _grid(truth)
    own = default_result.unadjusted()
    for k in range(N_FRAMES):
        a = adjusted.frame_to_base(k, g, "local")
        b = own.frame_to_base(k, g, "local")
        assert np.abs(a - b).max() < 0.05, k
        assert _map_error(adjusted, truth, k, "local") < _map_error(own, truth, k, "local") + 0.005
    for k in range(N_FRAMES - 1):
        assert (
            _pair_error(adjusted, truth, k, "local") < _pair_error(own, truth, k, "local") + 0.005
        )


def test_records_say_how_each_frame_was_adjusted(adjusted):
    for k in range(N_FRAMES):
        a = adjusted.records[k].stats["adjustment"]
        assert a["flagged"] == ""
        assert 0 <= a["predicted_error_px"] < 0.5
        assert a["n_links"] > 100
        assert tuple(a["window"]) in ((0, 4), (2, 6))
        if k:
            assert a["n_controls"] > 50 and a["control_rms_px"] is not None
    assert load_config(adjusted.out_dir).adjust == SMALL


def _records(out: Path) -> list[dict]:
    recs = []
    for k in range(N_FRAMES):
        rec = json.loads((out / "frames" / f"{k:06d}.json").read_text())
        rec["stats"].pop("time_s", None)
        local = rec["stats"].get("local", {})
        for key in [key for key in local if key.startswith("time")]:
            local.pop(key)
        recs.append(rec)
    return recs


def test_interrupted_adjustment_resumes_to_the_same_bits(sim_seq, adjusted, tmp_path):
    out = tmp_path / "out"
    cancel = threading.Event()

    def stop_after_three(done, total):
        if done >= 3:
            cancel.set()

    run(sim_seq, out, config=_config(), cancel=cancel, adjust_progress=stop_after_three)
    partial = registration.load(out)
    assert [partial.is_adjusted(k) for k in range(N_FRAMES)].count(True) == 3
    run(sim_seq, out, config=_config(), resume=True)
    a, b = _records(adjusted.out_dir), _records(out)
    for k in range(N_FRAMES):
        assert {x: a[k][x] for x in a[k] if x != "stats"} == {
            x: b[k][x] for x in b[k] if x != "stats"
        }
        assert a[k]["stats"] == b[k]["stats"], k


def test_links_stored_while_registering_give_the_adjustment_to_the_bit(
    sim_seq, tmp_path, monkeypatch
):
    """The links measured as the frames are registered (:mod:`registration.run.chunk_links`)
    are stored with the frames' arrays, every pair at the adjustment's steps, and spare the
    adjustment reading the frames again; an adjustment that measures every link itself from the
    frames ends with the same records and arrays, bit for bit."""
    import registration.run.adjust as adjust_module
    from registration.adjustment import links_from_arrays

    decoded = []
    to_grey = adjust_module.to_grey
    monkeypatch.setattr(adjust_module, "to_grey", lambda f: (decoded.append(1), to_grey(f))[1])
    stored = run(sim_seq, tmp_path / "stored", config=_config())
    pairs = {}
    for k in range(N_FRAMES):
        pairs.update(links_from_arrays(stored.stored_links(k)))
    assert set(pairs) == {(k, k + s) for s in (1, 2) for k in range(N_FRAMES - s)}
    assert all(len(links.src_k) > 100 for links, _ in pairs.values())
    assert decoded == []

    monkeypatch.setattr(adjust_module, "_stored_links", lambda result: None)
    measured = run(sim_seq, tmp_path / "measured", config=_config())
    assert len(decoded) == N_FRAMES  # the patch took: this adjustment read every frame
    a, b = _records(stored.out_dir), _records(measured.out_dir)
    for k in range(N_FRAMES):
        assert a[k]["adjusted_model"] == b[k]["adjusted_model"], k
        assert a[k]["stats"]["adjustment"] == b[k]["stats"]["adjustment"], k
        xa, xb = stored.arrays(k), measured.arrays(k)
        for name in xa:
            assert np.array_equal(xa[name], xb[name], equal_nan=xa[name].dtype.kind == "f"), name


def test_a_stored_link_stands_only_under_the_key_of_what_it_was_measured_through(sim_seq, adjusted):
    """The adjustment takes a stored pair of links only when its key is that of the models,
    lens and settings it would measure them through now (a frame whose start model the
    analyst's map points moved measures them again): a planted pair under the right key is
    used as it is, the same pair under another key is measured again from the frames."""
    from dataclasses import replace as dc_replace

    from registration.adjustment import FrameLinks, link_key
    from registration.io import open_frames
    from registration.run.adjust import _evidence

    evidence = _evidence(adjusted, open_frames(sim_seq / "frames"), SMALL)
    probes, matcher = SMALL.probes, SMALL.link_matcher
    measured = evidence.links(1, 2, probes, matcher)
    assert len(measured.src_k) > 100
    planted = FrameLinks(1, 2, measured.src_k[:10] + 5.0, measured.src_l[:10])
    key = link_key(evidence.models[1], evidence.models[2], evidence.lens, probes, matcher)
    for stored_key, expected in ((key, planted), (key[::-1].copy(), measured)):
        stored = lambda k, j, sk=stored_key: (planted, sk)  # noqa: E731
        ev = dc_replace(evidence, stored_links=stored, _links={}, _probes={})  # a fresh cache
        got = ev.links(1, 2, probes, matcher)
        assert np.array_equal(got.src_k, expected.src_k)
        assert np.array_equal(got.src_l, expected.src_l)


def test_register_adjust_reports_on_the_command_line(sim_seq, tmp_path, capsys):
    out = tmp_path / "out"
    truth = load_truth(sim_seq)
    fx, fy, bx, by = seed_for(sim_seq)
    code = cli_main([
        "register", "--frames", str(sim_seq / "frames"), "--base", str(sim_seq / "base.png"),
        "--gamma", str(truth.gamma), "--seed", f"{fx},{fy},{bx},{by}", "--out", str(out),
        "--adjust", "--json",
    ])  # fmt: skip
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_adjusted"] == N_FRAMES
    assert summary["flagged"] == []
    assert load_config(out).adjust == SequenceAdjustConfig()


def _strip_adjustment(out: Path, frames) -> None:
    """The folder as each frame's own registration left it (the default preset adjusts)."""
    from registration.run.records import read_record
    from registration.run.result_folder import ResultLock
    from registration.run.writer import ResultWriter

    writer = ResultWriter(out, ResultLock(out).acquire(), frames)
    try:
        for k in range(N_FRAMES):
            rec = read_record(out, k)
            stats = {n: v for n, v in rec.stats.items() if n != "adjustment"}
            writer.write_record(k, replace(rec, adjusted_model=None, stats=stats))
    finally:
        writer.close()


def _plant_offset(out: Path, frames, k: int, offset) -> None:
    """Frame ``k`` registered ``offset`` base px off, as a frame whose own registration went
    wrong: its model and its control points' map positions moved together."""
    from registration.run.records import read_record
    from registration.run.result_folder import ResultLock
    from registration.run.writer import ResultWriter

    rec = read_record(out, k)
    model = json.loads(json.dumps(rec.model))
    model["dst_norm"]["center"] = list(np.add(model["dst_norm"]["center"], offset))
    arrays = dict(np.load(out / "frames" / f"{k:06d}.npz"))
    arrays["dst"] = arrays["dst"] + np.asarray(offset)
    writer = ResultWriter(out, ResultLock(out).acquire(), frames)
    try:
        writer.write_frame(k, replace(rec, model=model), arrays)
    finally:
        writer.close()


@pytest.mark.parametrize("offset", [(9.0, 12.0), (18.0, 24.0)])
def test_a_frame_registered_off_is_put_back_or_flagged(sim_seq, default_result, tmp_path, offset):
    """Frame 3 15 base px off: its neighbours are still found in it (the probes search 8 frame
    px around where its model puts them), the links put it back (measured: 1.08 px from the
    truth, predicting 0.81) and its control points, which agree with each other but not with
    the links, weigh as little as their residuals show; its local stage, as far off, follows
    its links too (measured 15.0 -> 0.20 px). 30 px off: no link survives, and it is flagged.
    Either way its neighbours are not pulled, at either stage."""
    from registration.io import open_frames
    from registration.run.adjust import adjust_result
    from registration.run.result_folder import ResultLock
    from registration.run.writer import ResultWriter

    out = tmp_path / "out"
    shutil.copytree(default_result.out_dir, out)
    frames = open_frames(sim_seq / "frames")
    _strip_adjustment(out, frames)
    _plant_offset(out, frames, 3, offset)
    writer = ResultWriter(out, ResultLock(out).acquire(), frames)
    try:
        adjust_result(writer, frames, SMALL)
    finally:
        writer.close()
    truth = load_truth(sim_seq)
    result = registration.load(out)
    planted = _map_error(result.unadjusted(), truth, 3)
    assert planted > 4.5
    adjustment = result.records[3].stats["adjustment"]
    if np.hypot(*offset) < 20:
        assert _map_error(result, truth, 3) < 1.5
        assert adjustment["control_rms_px"] > 10 and adjustment["n_links"] > 50
        assert adjustment["predicted_error_px"] > 0.5  # not at the others' noise
        assert _map_error(result.unadjusted(), truth, 3, "local") > 4.5
        assert _map_error(result, truth, 3, "local") < 0.5
    else:
        assert adjustment["flagged"] == "no links to its neighbours"
        # evaluate says so, and checks the flag against the truth.
        report = evaluate_truth(result, truth).to_markdown()
        assert "- frame 3: no links to its neighbours" in report
        assert "1 of 6 adjusted frames are worse than 2 px" in report
        assert "0 of them unflagged (none); 0 good frames flagged (none)" in report
    for k in (1, 2, 4, 5):
        own = _map_error(default_result.unadjusted(), truth, k)
        assert _map_error(result, truth, k) < own + 0.1, k
        own_local = _map_error(default_result.unadjusted(), truth, k, "local")
        assert _map_error(result, truth, k, "local") < own_local + 0.01, k
        assert result.records[k].stats["adjustment"]["flagged"] == ""


def test_a_blank_frame_fails_and_the_others_are_adjusted_around_it(
    sim_seq, default_result, tmp_path
):
    frames_dir = tmp_path / "frames"
    shutil.copytree(sim_seq / "frames", frames_dir)
    blank = sorted(frames_dir.iterdir())[3]
    image = cv2.imread(str(blank))
    cv2.imwrite(str(blank), np.full_like(image, 128))
    result = run(sim_seq, tmp_path / "out", frames_dir=frames_dir, config=_config())
    truth = load_truth(sim_seq)
    assert result.status(3) == "failed" and not result.is_adjusted(3)
    for k in (0, 1, 2, 4, 5):
        assert result.is_adjusted(k)
        assert result.records[k].stats["adjustment"]["flagged"] == ""
        own = _map_error(default_result.unadjusted(), truth, k)
        assert _map_error(result, truth, k) < own + 0.05, k


def test_the_adjustment_runs_blas_on_one_thread(monkeypatch):
    """The adjustment's products are small: OpenBLAS's threads cost more CPU than they save
    (the real flyover: 0.031 -> 0.0275 s per frame), so it runs them on one thread, and the
    threads the caller had are back afterwards."""
    from threadpoolctl import threadpool_info

    from registration.run import adjust

    seen = []
    monkeypatch.setattr(
        adjust, "_adjust_result",
        lambda *a: seen.append([p["num_threads"] for p in threadpool_info()
                                if p["user_api"] == "blas"]) or 0,
    )  # fmt: skip
    before = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    assert adjust.adjust_result(None, None, None) == 0
    assert seen and seen[0] and all(n == 1 for n in seen[0])
    assert [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"] == before
