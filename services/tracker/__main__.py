"""`python -m services.tracker`: the tracker service alone (same as `etam tracker`)."""

import sys

from services.cli import run

if __name__ == "__main__":
    sys.argv.insert(1, "tracker")
    run()
