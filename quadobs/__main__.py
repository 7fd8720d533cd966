"""``python -m quadobs``: the ``quadobs`` command."""

import sys

from quadobs.cli import main

if __name__ == "__main__":
    sys.exit(main())
