"""``python -m svcode_core.cli``: the same as the ``svcode`` command."""

import sys

from . import main

sys.exit(main())
