"""`python -m services.camera`: the camera service alone (same as `etam camera`)."""

import sys

from services.cli import run

if __name__ == "__main__":
    sys.argv.insert(1, "camera")
    run()
