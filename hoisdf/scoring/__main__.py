"""``python -m hoisdf.scoring SUBCOMMAND ...``: the ``hoisdf score`` command without the console script."""

import sys

from hoisdf.scoring.cli import main

sys.exit(main())
