"""Benchmark suites behind ``aerialreg bench`` (not part of the installed package: they run from
a source checkout). Each module ``benchmarks/<suite>.py`` defines ``TITLE`` and
``run(opts) -> dict``; the dict holds the raw figures and a ``"markdown"`` table. Benchmarks
compare against a baseline measured in the same run and report ratios.

Run them with ``aerialreg bench SUITE ...`` or ``python -m benchmarks SUITE ...`` from the
checkout."""

SUITES = (
    "distortion",
    "simulate",
    "register",
    "heading",
    "scaleout",
    "srif",
    "export",
    "app",
    "flyover",
    "traffic",
)
