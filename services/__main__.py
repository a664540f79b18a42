"""`python -m services`: the `etam` command."""

from services.cli import run

if __name__ == "__main__":
    run()
