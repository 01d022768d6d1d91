"""``python -m benchmarks SUITE ...``: the same as ``aerialreg bench SUITE ...``."""

import sys

from app.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
