"""tools/mutate.py (the mutation check, not run in CI) stays applicable: every planted bug's
search text occurs in today's code as often as it says and its tests exist (the tool's own
``--check``), so a refactor that moves the code a bug is planted in fails here instead of
turning into a silent "does not apply" in the next mutation run."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_every_planted_bug_applies_to_todays_code():
    spec = importlib.util.spec_from_file_location("aerialreg_mutate", REPO / "tools/mutate.py")
    mutate = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mutate
    spec.loader.exec_module(mutate)
    assert len(mutate.MUTATIONS) >= 25
    assert mutate.check(mutate.MUTATIONS, REPO) == []
