"""``python -m glossrig``: the same command line as the ``glossrig`` script."""
import sys

from glossrig.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
