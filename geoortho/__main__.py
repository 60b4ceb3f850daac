"""``python -m geoortho``."""

import sys

from geoortho.processing.cli import main

if __name__ == "__main__":
    sys.exit(main())
