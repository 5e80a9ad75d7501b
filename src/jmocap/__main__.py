"""``python -m jmocap ...``: the same as the ``jmocap`` command."""

import sys

from jmocap.cli import main

if __name__ == "__main__":
    sys.exit(main())
