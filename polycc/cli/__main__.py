"""`python -m polycc.cli` = `polycc`."""

import sys

from polycc.cli import main

sys.exit(main())
