"""``python -m volreg``: the same as the ``volreg`` command."""

from volreg.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
