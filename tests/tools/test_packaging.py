"""The package as a wheel: every module and the app's static assets are inside, and the app finds
its assets when run from the installed layout (not the source checkout).

Builds from a copy of the sources (so no build/ or egg-info lands in the checkout), offline and
without build isolation: needs the ``wheel`` package (the test extras install it).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ASSETS = ("camera.js", "app.css", "events.js", "pointer.js")

pytest.importorskip("wheel", reason="building a wheel offline needs the 'wheel' package")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("app", "registration", "static"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path_factory.mktemp("dist")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation"]
    cmd += ["--no-index", "-q", "-w", str(dist), str(src)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    (whl,) = dist.glob("aerialreg-*.whl")
    return whl


def test_wheel_holds_every_module_and_the_static_assets(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for asset in ASSETS:
        assert f"app/static/{asset}" in names, sorted(n for n in names if "static" in n)
    modules = {
        p.relative_to(ROOT).as_posix()
        for pkg in ("app", "registration")
        for p in (ROOT / pkg).rglob("*.py")
        if "__pycache__" not in p.parts
    }
    missing = sorted(modules - names)
    assert not missing, f"modules left out of the wheel: {missing}"
    for asset in ASSETS:  # the shipped files are the repository's
        assert (
            zipfile.ZipFile(wheel).read(f"app/static/{asset}")
            == (ROOT / "static" / asset).read_bytes()
        )


def test_installed_layout_finds_its_assets_outside_the_checkout(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = dict(os.environ, PYTHONPATH=str(site))
    probe = (
        "import app, app.gui.assets as a, app.gui.server, app.gui.views.sequence.export;"
        "print(app.__file__); print(a.STATIC_DIR);"
        "print(all(len(a.read_asset(n)) > 0 for n in a.ASSETS))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    module, static, ok = out.stdout.split()
    assert Path(module).is_relative_to(site) and Path(static) == site / "app" / "static"
    assert ok == "True"
    cli = subprocess.run(
        [sys.executable, "-m", "app.cli", "app", "--help"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
    )
    assert cli.returncode == 0 and "usage: aerialreg app" in cli.stdout, cli.stderr[-2000:]


def test_benchmarks_stay_out_of_the_wheel_and_bench_says_so(wheel, tmp_path):
    """The benchmark suites are a developer tool of the checkout (benchmarks/), not installed;
    ``aerialreg bench`` from an installed package says where they are in one line."""
    names = zipfile.ZipFile(wheel).namelist()
    assert not [n for n in names if n.startswith(("benchmarks/", "app/bench/"))]
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = dict(os.environ, PYTHONPATH=str(site))
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", "bench", "simulate"],
        cwd=tmp_path, env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "aerialreg bench: error: aerialreg bench runs from a source checkout of aerialreg: the "
        "benchmarks/ folder is not installed with the package (clone the repository, pip install "
        "-e it and run the command there)"
    ]
