"""``python -m traffictwin.cli``: the ``traffictwin`` command."""

import sys

from traffictwin.cli import main

if __name__ == "__main__":
    sys.exit(main())
