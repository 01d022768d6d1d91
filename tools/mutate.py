"""Mutation check: plant named bugs one at a time and report which tests catch each.

Not part of CI (it runs a test subset once per bug, ~1 h on 2 cores). Each mutation is a
search/replace on one source file, applied to a temporary copy of the repository (never to the
working tree); the mutation's test subset then runs in that copy, and every test that passed on
the unmutated copy and fails on the mutated one has caught the bug. The script prints a markdown
table ``bug -> caught by`` (``NOT CAUGHT`` when no test notices) and can write it as JSON.

Usage::

    python tools/mutate.py                      # every mutation, its own test subset
    python tools/mutate.py --only fine_removed dither_disabled
    python tools/mutate.py --without-shared     # as a clone without ../shared/data would run
    python tools/mutate.py --repo DIR           # mutate another checkout (e.g. an older main);
                                                # test files it lacks are left out of the subsets
    python tools/mutate.py --list

A mutation whose search text no longer occurs exactly as often as it expects is reported as
``PATCH DOES NOT APPLY`` (the code moved on: update the mutation), never silently skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Test files of the end-to-end layer: whole-sequence runs against the simulator's truth.
E2E = [
    "tests/e2e/test_accuracy.py",
    "tests/e2e/test_reference_frame.py",
    "tests/run/test_pipeline.py",
]


@dataclass(frozen=True)
class Mutation:
    """A planted bug: ``patches`` are ``(search, replace, count)`` on ``path``, or ``(search,
    replace, count, other_path)`` where one bug spans two files (each search text
    must occur exactly ``count`` times); ``tests`` are the pytest paths or node ids to run."""

    name: str
    bug: str
    path: str
    patches: tuple[tuple, ...]
    tests: tuple[str, ...]
    tags: tuple[str, ...] = field(default=())


def _m(name, bug, path, patches, tests, tags=()):
    return Mutation(name, bug, path, tuple(patches), tuple(tests), tuple(tags))


MUTATIONS: list[Mutation] = [
    # -- the list (integration layer), translated to today's code -------------------
    _m(
        "fine_removed",
        "fine step removed: `fit_fine` keeps the coarse projective",
        "registration/global_registration/fine.py",
        [
            (
                "if n < 3 * start.min_samples and check_support and isinstance(initial, Projective):",
                "if isinstance(initial, Projective):",
                1,
            )
        ],  # fmt: skip
        ["tests/global_registration/test_global_registration.py", *E2E, "tests/gis/test_export.py"],
    ),
    _m(
        "seed_gate_open",
        "seed gate dropped: `heading.gate_by_prior` passes every match",
        "registration/global_registration/heading.py",
        [
            (
                "return np.isfinite(dist) & (dist <= gate_radius_px(prior, p, config))",
                "return np.ones(len(p), bool)",
                1,
            )
        ],  # fmt: skip
        [
            "tests/global_registration/test_heading.py",
            "tests/global_registration/test_coarse.py",
            "tests/global_registration/test_global_registration.py",
            *E2E,
        ],  # fmt: skip
    ),
    _m(
        "frames_before_reference_dropped",
        "frames before the reference frame never processed",
        "registration/run/chunks.py",
        [("        *range(reference_frame - 1, -1, -1),\n", "", 1)],
        [*E2E, "tests/gis/test_export.py"],
    ),
    _m(
        "evaluation_reference_is_frame_0",
        "evaluation always uses frame 0 as the reference frame",
        "registration/evaluation/truth.py",
        [
            ("ref = int(result.reference_frame)", "ref = 0", 2),
            (
                "ref = int(result.reference_frame)",
                "ref = 0",
                1,
                "registration/evaluation/points.py",
            ),
        ],  # fmt: skip
        ["tests/evaluation/test_evaluation.py", *E2E],
    ),
    _m(
        "harris_ignores_centre",
        "`HarrisModel` ignores a given distortion centre",
        "registration/lens/radial.py",
        [("        if self.center is None:\n", "        if True:\n", 1)],
        [
            "tests/lens/test_distortion.py",
            "tests/lens/test_calibration.py",
            "tests/cli/test_cli_distortion.py",
        ],
    ),
    _m(
        "overlay_base_only",
        "registered overlay renders only the base map",
        "registration/render/video.py",
        [("overlay(image, mid, mask=mask)", "overlay(mid, mid, mask=mask)", 1)],
        [
            "tests/render/test_render.py",
            "tests/render/test_render_content.py",
            "tests/e2e/test_reference_frame.py",
            "tests/gis/test_export.py",
        ],  # fmt: skip
    ),
    _m(
        "field_image_components_swapped",
        "field images: the dx image shows dy and the dy image dx",
        "registration/render/figures.py",
        [
            (
                'for c, title in ((0, "dx px"), (1, "dy px")):',
                'for c, title in ((1, "dx px"), (0, "dy px")):',
                1,
            )
        ],  # fmt: skip
        ["tests/render/test_render.py", "tests/render/test_render_content.py"],
    ),
    _m(
        "previous_frame_fallback_disabled",
        "intra-sensor templates never fall back to the previous frame",
        "registration/global_registration/intra_points.py",
        [
            (
                "    fallbacks = []\n    if prev is not None:\n",
                "    fallbacks = []\n    if False:\n",
                1,
            )
        ],  # fmt: skip
        [
            "tests/global_registration/test_global_registration.py",
            "tests/matching/test_templates.py",
            *E2E,
        ],
    ),
    _m(
        "paper_preset_is_default",
        "the paper preset returns the default configuration",
        "registration/run/config.py",
        [
            (
                "def _paper() -> PipelineConfig:\n",
                "def _paper() -> PipelineConfig:\n    return _default()\n",
                1,
            )
        ],  # fmt: skip
        ["tests/run/test_config.py", *E2E],
    ),
    _m(
        "dither_disabled",
        "dithered NCC disabled (no re-correlation at the sub-pixel estimate)",
        "registration/matching/ncc_peaks.py",
        [("    for _ in range(config.dither_iterations):\n", "    for _ in range(0):\n", 1)],
        [
            "tests/matching/test_templates.py",
            "tests/global_registration/test_global_registration.py",
        ],
        tags=("real-image",),
    ),
    # -- controls: bugs the issue found caught; they must stay caught ------------------------
    _m(
        "gamma_sign_flipped",
        "Harris correction uses +γ (raw -> corrected with the wrong sign)",
        "registration/lens/radial.py",
        [
            (
                "return self._apply(as_points(xy), -self.gamma, self.c, self.r_n)",
                "return self._apply(as_points(xy), self.gamma, self.c, self.r_n)",
                1,
            )
        ],  # fmt: skip
        ["tests/lens/test_distortion.py"],
    ),
    _m(
        "result_ignores_field",
        "the local stage of a result ignores its displacement field (field zeroed)",
        "registration/run/result.py",
        [
            (
                'model, field, consistency = self.local_stage(k) if stage == "local" else (None,) * 3',
                "model, field, consistency = (None,) * 3",
                2,
            )
        ],
        ["tests/run/test_result.py", *E2E],
    ),
    # -- the new modules ---------------------------------------------------------------------
    _m(
        "heading_off_by_90",
        "one-seed heading estimate off by 90°",
        "registration/global_registration/heading.py",
        [("        float(peak_heading),\n", "        float((peak_heading + 90.0) % 360.0),\n", 1)],
        ["tests/global_registration/test_heading.py", "tests/global_registration/test_coarse.py"],
        tags=("real-image",),
    ),
    _m(
        "guided_matching_disabled",
        "coarse step without guided matching",
        "registration/global_registration/coarse_fit.py",
        [("    if config.guided and len(fk):\n", "    if False and len(fk):\n", 1)],
        [
            "tests/global_registration/test_coarse.py",
            "tests/global_registration/test_heading.py",
            *E2E,
        ],
    ),
    _m(
        "correlation_on_intensity",
        "coarse correlation rounds correlate intensity instead of gradient magnitude",
        "registration/global_registration/gradient_correlation.py",
        [
            (
                "gradient_magnitude(frame_grey), gradient_magnitude(base)",
                "to_grey(frame_grey), to_grey(base)",
                1,
            ),
            (
                "    downscale_mask,\n    gradient_magnitude,\n",
                "    downscale_mask,\n    gradient_magnitude,\n    to_grey,\n",
                1,
            ),
        ],  # fmt: skip
        ["tests/global_registration/test_coarse.py", *E2E],
    ),
    _m(
        "model_choice_richest",
        "spatial cross-validation always keeps the richest model",
        "registration/geometry/model_choice.py",
        [("        if err < (1.0 - margin) * best_err:\n", "        if True:\n", 1)],
        [
            "tests/geometry/test_robust.py",
            "tests/geometry/test_model_choice.py",
            "tests/global_registration/test_coarse.py",
            *E2E,
        ],
    ),
    _m(
        "reqcon_outlier_rule_never_stops",
        "REQCON's outlier rule never stops: drops 5 % per round like the paper's rule",
        "registration/geometry/reqcon_fit.py",
        [
            ("        if n_out == 0:\n", "        if False:\n", 1),
            ("        n_drop = min(n_drop, n_out)\n", "", 1),
        ],  # fmt: skip
        ["tests/geometry/test_robust.py", "tests/geometry/test_model_choice.py", *E2E],
    ),
    _m(
        "reqcon_never_drops",
        "REQCON never drops a point",
        "registration/geometry/reqcon_fit.py",
        [("    kept[worst] = False\n", "    pass\n", 1)],
        ["tests/geometry/test_robust.py", *E2E],
    ),
    _m(
        "intra_gate_open",
        "intra-sensor prediction gate passes every match",
        "registration/global_registration/intra.py",
        [
            (
                "return np.linalg.norm(predict(fxy) + shift - bxy, axis=1) < limit",
                "return np.linalg.norm(predict(fxy) + shift - bxy, axis=1) < np.inf",
                1,
            )
        ],  # fmt: skip
        ["tests/global_registration/test_global_registration.py", *E2E],
    ),
    _m(
        "structure_anchor_ignored",
        "template matches attributed to the template centre instead of the structure centroid",
        "registration/matching/templates.py",
        [
            (
                '    use_structure = config.warp_reference and config.anchor == "structure"\n',
                "    use_structure = False\n",
                1,
            )
        ],  # fmt: skip
        ["tests/matching/test_templates.py"],
        tags=("real-image",),
    ),
    _m(
        "mid_base_without_reference_field",
        "the mid base image is rendered without the reference frame's own field",
        "registration/run/pipeline.py",
        [
            (
                "mid, valid = render_to_base(frame, camera, model, (0, 0, wb, hb), field_)",
                "mid, valid = render_to_base(frame, camera, model, (0, 0, wb, hb))",
                1,
            )
        ],  # fmt: skip
        [*E2E],
    ),
    _m(
        "warp_pixel_grid_half_pixel",
        "`warp.pixel_grid` half a pixel off in x (shared by test inputs and code)",
        "registration/geometry/warp.py",
        [
            (
                "np.arange(width, dtype=np.float32), np.arange(height",
                "np.arange(width, dtype=np.float32) + 0.5, np.arange(height",
                1,
            )
        ],  # fmt: skip
        [
            "tests/geometry/test_warp.py",
            "tests/lens/test_distortion.py",
            "tests/matching/test_templates.py",
            "tests/render/test_render.py",
        ],  # fmt: skip
    ),
    _m(
        "warp_lattice_shifted",
        "`warp.source_map_from_function` lattice nodes a pixel off (step > 1)",
        "registration/geometry/warp.py",
        [
            (
                "    xs = (np.arange(gx) - 1 + 0.5) * step - 0.5\n",
                "    xs = (np.arange(gx) - 1 + 0.5) * step + 0.5\n",
                1,
            )
        ],  # fmt: skip
        [
            "tests/geometry/test_warp.py",
            "tests/render/test_render.py",
            "tests/matching/test_templates.py",
        ],
    ),
    _m(
        "atomic_write_in_place",
        "`io.write_bytes_atomic` writes the target in place (not atomic)",
        "registration/io/atomic.py",
        [
            (
                "    with atomic_path(path) as tmp:\n        tmp.write_bytes(data)\n",
                "    Path(path).parent.mkdir(parents=True, exist_ok=True)\n"
                "    Path(path).write_bytes(data)\n",
                1,
            ),
        ],  # fmt: skip
        ["tests/io/test_io.py", "tests/cli/test_bad_input.py"],
    ),
    _m(
        "result_nan_outside_frame_lost",
        "`frame_to_base` maps points outside the frame instead of NaN",
        "registration/run/result.py",
        [("        out[~self._inside_frame(xy)] = np.nan\n", "", 1)],
        ["tests/run/test_result.py", *E2E],
    ),
    # -- the survivors of an independent audit (issue "Nothing mixed, nothing lost") --------
    _m(
        "resume_sample_hash_self",
        "the resume identity check compares a frame's sample hash with itself",
        "registration/io/frames.py",
        [
            (
                'if o.get("sample_sha256") != n.get("sample_sha256"):',
                'if n.get("sample_sha256") != n.get("sample_sha256"):',
                1,
            )
        ],  # fmt: skip
        ["tests/run/test_identity.py"],
    ),
    _m(
        "host_any_ip_literal",
        "the app accepts any IP-literal Host while bound to loopback",
        "app/gui/security.py",
        [
            (
                "if host not in self.names and not (self.any_interface and _is_ip(host)):",
                "if host not in self.names and not _is_ip(host):",
                1,
            )
        ],  # fmt: skip
        ["tests/app/test_security.py"],
    ),
    _m(
        "reqcon_scale_over_dropped",
        "REQCON's noise scale taken over the points it already dropped",
        "registration/geometry/reqcon_fit.py",
        [
            (
                "sigma = float(np.median(rs[kept])) / _RAYLEIGH_MEDIAN",
                "sigma = float(np.median(rs)) / _RAYLEIGH_MEDIAN",
                1,
            )
        ],
        ["tests/geometry/test_robust.py"],
    ),
    _m(
        "fast_path_one_condition",
        "the fast intra-sensor path confirmed when only one of its two conditions holds",
        "registration/global_registration/predicted_coarse.py",
        [
            (
                "if n_in < min_inliers or n_in < MIN_INLIER_SHARE * n:",
                "if n_in < min_inliers and n_in < MIN_INLIER_SHARE * n:",
                1,
            )
        ],
        ["tests/global_registration/test_fast_coarse.py"],
    ),
    _m(
        "click_refit_kept_when_missing",
        "the click refit kept even when it still misses the click",
        "registration/global_registration/fine.py",
        [
            (
                "if now < was and (now <= limit_px or was - now >= limit_px / 2):",
                "if now < was:",
                1,
            )
        ],
        ["tests/global_registration/test_click_refit.py"],
    ),
    _m(
        "click_refit_only_within_the_distance",
        "a refit on the clicked plane discarded when the click is 8-10 px off",
        "registration/global_registration/fine.py",
        [
            (
                "if now < was and (now <= limit_px or was - now >= limit_px / 2):",
                "if now < was and now <= limit_px:",
                1,
            )
        ],
        ["tests/global_registration/test_click_refit.py"],
    ),
    _m(
        "table2_points_from_frame_0",
        "Table 2's ground points taken from frame 0 instead of the reference frame",
        "registration/evaluation/truth.py",
        [
            (
                "b_pts = truth.frame_to_base(ref, table_points(",
                "b_pts = truth.frame_to_base(0, table_points(",
                1,
            )
        ],
        ["tests/evaluation/test_evaluation.py"],
    ),
]


# --------------------------------------------------------------------------------------------
# Running


def _copy_repo(src: Path, dst: Path, shared: Path | None) -> Path:
    """Copy the repository's files (not .git, caches or build output) into ``dst/repo`` and link
    ``dst/shared`` to ``shared`` (None: no link), where the tests look for the imagery."""
    repo = dst / "repo"
    ignore = shutil.ignore_patterns(
        ".git", "__pycache__", "*.pyc", ".pytest_cache", ".ruff_cache", "*.egg-info", "build",
        "dist", "out", "tmp",
    )  # fmt: skip
    shutil.copytree(src, repo, ignore=ignore, symlinks=True)
    if shared is not None and shared.exists():
        (dst / "shared").symlink_to(shared.resolve())
    return repo


def _files(m: Mutation) -> list[str]:
    """The files ``m`` patches, ``m.path`` first."""
    out = [m.path]
    for patch in m.patches:
        if len(patch) == 4 and patch[3] not in out:
            out.append(patch[3])
    return out


def _apply(repo: Path, m: Mutation) -> str:
    """Apply ``m`` in place (every patch or none); "" or the reason it does not apply."""
    texts = {f: (repo / f).read_text() for f in _files(m)}
    for search, replace, count, *where in m.patches:
        f = where[0] if where else m.path
        found = texts[f].count(search)
        if found != count:
            return f"search text found {found} times, expected {count}: {search.strip()[:60]!r}"
        texts[f] = texts[f].replace(search, replace)
    for f, text in texts.items():
        (repo / f).write_text(text)
    return ""


def _selection(repo: Path, tests: tuple[str, ...]) -> list[str]:
    """The tests that exist in ``repo`` (a file path, or ``file::name``)."""
    return [t for t in tests if (repo / t.split("::")[0]).is_file()]


def _pytest(repo: Path, tests: list[str], xml: Path, timeout: int) -> tuple[set[str], set[str]]:
    """Run ``tests`` in ``repo``; ``(passed, failed)`` node ids (errors count as failed)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo)
    env["PYTHONDONTWRITEBYTECODE"] = "1"  # a mutated .pyc must never outlive its mutation
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not browser",
           f"--timeout={timeout}", f"--junitxml={xml}", *tests]  # fmt: skip
    subprocess.run(cmd, cwd=repo, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    passed, failed = set(), set()
    if not xml.is_file():
        return passed, {"<pytest did not run>"}
    for case in ET.parse(xml).getroot().iter("testcase"):
        name = f"{case.get('classname', '').replace('.', '/')}.py::{case.get('name')}"
        name = name.replace("tests/", "", 1)
        kinds = {child.tag for child in case}
        if kinds & {"failure", "error"}:
            failed.add(name)
        elif "skipped" not in kinds:
            passed.add(name)
    return passed, failed


def _check_import(repo: Path) -> None:
    """The copy's modules, not an installed aerialreg, must be the ones imported."""
    env = dict(os.environ, PYTHONPATH=str(repo), PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run(
        [sys.executable, "-c", "import registration, app; print(registration.__file__)"],
        cwd=repo, env=env, capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    if not Path(out).resolve().is_relative_to(repo.resolve()):
        raise SystemExit(f"the copy is not what Python imports ({out}); check PYTHONPATH")


def check(mutations: list[Mutation], src: Path) -> list[str]:
    """Problems of mutations that do not apply to ``src`` (nothing is run)."""
    problems = []
    with tempfile.TemporaryDirectory(prefix="aerialreg-mutate-") as tmp:
        repo = _copy_repo(src, Path(tmp), None)
        for m in mutations:
            originals = {f: (repo / f).read_text() for f in _files(m)}
            problem = _apply(repo, m)
            for f, text in originals.items():
                (repo / f).write_text(text)
            if problem:
                problems.append(f"{m.name}: {problem}")
            missing = sorted(set(m.tests) - set(_selection(repo, m.tests)))
            if missing:
                problems.append(f"{m.name}: no such test file {', '.join(missing)}")
    return problems


def run(
    mutations: list[Mutation],
    src: Path,
    shared: Path | None,
    timeout: int,
    log=print,
    all_tests: bool = False,
) -> list[dict]:
    """Apply each mutation in turn to one copy of ``src`` and run its tests (``all_tests``: the
    whole non-browser suite instead); rows of the table, see :func:`markdown`."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="aerialreg-mutate-") as tmp:
        repo = _copy_repo(src, Path(tmp), shared)
        _check_import(repo)

        def selection(m: Mutation) -> list[str]:
            return ["tests"] if all_tests else _selection(repo, m.tests)

        union = sorted({t for m in mutations for t in selection(m)})
        log(f"control run of {len(union)} test files on the unmutated copy ...")
        t0 = time.perf_counter()
        base_pass, base_fail = _pytest(repo, union, Path(tmp) / "control.xml", timeout)
        log(
            f"  {len(base_pass)} passed, {len(base_fail)} failed ({time.perf_counter() - t0:.0f} s)"
        )
        for m in mutations:
            target = repo / m.path
            original = target.read_text() if target.is_file() else None
            row = {"name": m.name, "bug": m.bug, "file": m.path, "tests": list(m.tests)}
            problem = _apply(repo, m) if original is not None else f"{m.path} does not exist"
            if problem:
                row.update(status="does not apply", reason=problem, caught_by=[])
                log(f"{m.name}: PATCH DOES NOT APPLY ({problem})")
                rows.append(row)
                continue
            selected = selection(m)
            t0 = time.perf_counter()
            try:
                _, failed = _pytest(repo, selected, Path(tmp) / f"{m.name}.xml", timeout)
            finally:
                target.write_text(original)
            caught = sorted(failed - base_fail)
            row.update(
                status="caught" if caught else "not caught",
                caught_by=caught,
                selected=selected,
                time_s=round(time.perf_counter() - t0, 1),
            )
            log(f"{m.name}: {'caught by ' + str(len(caught)) if caught else 'NOT CAUGHT'} "
                f"({row['time_s']:.0f} s)")  # fmt: skip
            rows.append(row)
        for row in rows:
            row["control_failures"] = sorted(base_fail)
    return rows


def markdown(rows: list[dict], max_names: int = 4) -> str:
    out = ["| Planted bug | Caught by |", "|---|---|"]
    for r in rows:
        if r["status"] == "does not apply":
            cell = f"PATCH DOES NOT APPLY ({r['reason']})"
        elif not r["caught_by"]:
            cell = "**NOT CAUGHT**"
        else:
            names = [n.split("::")[-1] for n in r["caught_by"]]
            more = f" (+{len(names) - max_names} more)" if len(names) > max_names else ""
            cell = ", ".join(f"`{n}`" for n in names[:max_names]) + more
        out.append(f"| `{r['name']}`: {r['bug']} | {cell} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", nargs="+", metavar="NAME", help="run only these mutations")
    p.add_argument("--tag", help="run only mutations with this tag (e.g. real-image)")
    p.add_argument("--repo", type=Path, default=REPO, help="checkout to mutate (default: this)")
    p.add_argument(
        "--shared",
        type=Path,
        default=REPO.parent / "shared",
        help="the real imagery's folder (default: ../shared beside this repo)",
    )
    p.add_argument(
        "--without-shared",
        action="store_true",
        help="do not link ../shared: real-image tests skip, as in a bare clone",
    )
    p.add_argument("--check", action="store_true",
                   help="only check that every mutation applies and its tests exist")  # fmt: skip
    p.add_argument(
        "--tests",
        nargs="+",
        metavar="PATH",
        help="run these tests for every chosen mutation instead of its own subset",
    )
    p.add_argument("--all-tests", action="store_true",
                   help="run the whole non-browser suite for every mutation (slow)")  # fmt: skip
    p.add_argument("--timeout", type=int, default=600, help="per-test timeout, s")
    p.add_argument("--json", type=Path, help="also write the rows as JSON here")
    p.add_argument("--list", action="store_true", help="list the mutations and exit")
    args = p.parse_args(argv)
    chosen = MUTATIONS
    if args.only:
        unknown = sorted(set(args.only) - {m.name for m in MUTATIONS})
        if unknown:
            p.error(f"unknown mutation {unknown[0]!r}; --list shows them")
        chosen = [m for m in MUTATIONS if m.name in args.only]
    if args.tag:
        chosen = [m for m in chosen if args.tag in m.tags]
    if args.tests:
        chosen = [dataclasses.replace(m, tests=tuple(args.tests)) for m in chosen]
    if args.list:
        for m in chosen:
            print(f"{m.name:36s} {m.path:40s} {m.bug}")
        return 0
    if args.check:
        problems = check(chosen, args.repo.resolve())
        print("\n".join(problems) or f"all {len(chosen)} mutations apply")
        return 1 if problems else 0
    shared = None if args.without_shared else args.shared
    rows = run(chosen, args.repo.resolve(), shared, args.timeout,
               log=lambda s: print(s, file=sys.stderr, flush=True), all_tests=args.all_tests)  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    print(markdown(rows))
    missed = [r["name"] for r in rows if r["status"] != "caught"]
    if missed:
        print(f"\nnot caught or not applied: {', '.join(missed)}", file=sys.stderr)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
