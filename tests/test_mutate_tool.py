"""tools/mutate.py (the mutation check, not run in CI) stays applicable: every planted bug's
search text occurs in today's code as often as it says, so a refactor that moves the code a bug
is planted in shows here instead of as a silent "does not apply" in the next mutation run."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _mutate_module():
    spec = importlib.util.spec_from_file_location("aerialreg_mutate", REPO / "tools/mutate.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_every_planted_bug_applies_to_todays_code(tmp_path):
    mutate = _mutate_module()
    assert len(mutate.MUTATIONS) >= 25
    problems = []
    for m in mutate.MUTATIONS:
        copy = tmp_path / m.name
        (copy / m.path).parent.mkdir(parents=True)
        shutil.copy(REPO / m.path, copy / m.path)
        why = mutate._apply(copy, m)
        if why:
            problems.append(f"{m.name}: {why}")
        elif (copy / m.path).read_text() == (REPO / m.path).read_text():
            problems.append(f"{m.name}: applied but changed nothing")
    assert not problems, problems
