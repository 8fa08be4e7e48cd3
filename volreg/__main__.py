"""``python -m volreg``: the same as the ``volreg`` command."""

from volreg.cli import run

if __name__ == "__main__":
    run()
