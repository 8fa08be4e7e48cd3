"""``python -m volreg``: the same as the ``volreg`` command."""

from volreg._signals import exit_on_early_signals

exit_on_early_signals()  # before the command line's imports (again, should the package have been loaded first)

from volreg.cli import run  # noqa: E402

if __name__ == "__main__":
    run()
