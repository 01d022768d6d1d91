"""The README's typical headless run, as written: its commands are read from the README itself,
run in a fresh folder, and must succeed and register every frame near the truth."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from app.cli import main as cli_main

pytestmark = pytest.mark.e2e

README = Path(__file__).resolve().parents[2] / "README.md"


def typical_run() -> list[list[str]]:
    """The commands of the README's "A typical headless run" block (comments dropped)."""
    text = README.read_text(encoding="utf-8")
    m = re.search(r"A typical headless run:\s*```bash\n(.*?)```", text, re.S)
    assert m, "README has no 'A typical headless run' block"
    commands = []
    for line in m.group(1).splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            argv = shlex.split(line)
            assert argv[0] == "aerialreg", line
            commands.append(argv[1:])
    return commands


def test_the_readme_typical_run_works_as_written(tmp_path, monkeypatch, capsys):
    commands = typical_run()
    assert [c[0] for c in commands] == ["simulate", "register", "evaluate"]
    monkeypatch.chdir(tmp_path)
    for argv in commands:
        assert cli_main(argv) == 0, (argv, capsys.readouterr().err)
    err = capsys.readouterr().err
    # γ was estimated (the default), near the simulator's 0.7, and said so.
    m = re.search(r"gamma (-?[0-9.]+) ± ([0-9.]+) from the frames' motion", err)
    assert m and abs(float(m.group(1)) - 0.7) < 0.02, err
    out = Path(commands[1][commands[1].index("--out") + 1])
    result = json.loads((out / "result.json").read_text())
    from registration import load
    from registration.evaluation import evaluate_truth
    from registration.synth import load_truth

    res = load(out)
    assert result["n_frames"] == 25 and all(r.status == "ok" for r in res.records)
    report = evaluate_truth(res, load_truth(Path(commands[0][1])))
    local = [f["local"]["mean"] for f in report.per_frame]
    assert np.max(local) < 1.0, local
