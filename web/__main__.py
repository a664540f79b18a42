"""`python -m web`: the dashboard service alone (same as `etam web`)."""

import sys

from services.cli import run

if __name__ == "__main__":
    sys.argv.insert(1, "web")
    run()
