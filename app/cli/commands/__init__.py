"""One module per ``aerialreg`` subcommand. Each defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :mod:`app.cli` wires them up."""
