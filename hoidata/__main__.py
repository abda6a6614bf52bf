"""``python -m hoidata COMMAND ...``: the ``hoidata`` command without its console script on PATH (how
``python -m hoisdf.toy`` runs the data steps in a child process)."""

import sys

from hoidata.cli import main

sys.exit(main())
