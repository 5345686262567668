"""``python -m facenormals``: the ``facenormals`` command line."""

import sys

from facenormals.cli import main

if __name__ == "__main__":
    sys.exit(main())
