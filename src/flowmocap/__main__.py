"""``python -m flowmocap ...``: the ``flowmocap`` command, where its script is not on PATH."""

import sys

from flowmocap.cli import main

if __name__ == "__main__":
    sys.exit(main())
