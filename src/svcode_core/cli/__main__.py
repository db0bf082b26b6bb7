"""``python -m svcode_core.cli``: the same as the ``svcode`` command."""

import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
