"""Benchmark suites behind ``aerialreg bench``. Each module ``app/bench/<suite>.py`` defines
``TITLE`` and ``run(opts) -> dict``; the dict holds the raw figures and a ``"markdown"`` table.
Benchmarks compare against a baseline measured in the same run and report ratios."""
