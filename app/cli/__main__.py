"""``python -m app.cli ...``: the same as the ``aerialreg`` console command."""

import sys

from app.cli import main

sys.exit(main())
