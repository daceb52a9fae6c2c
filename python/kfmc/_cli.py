"""The ``kfmc`` console script: the command line of the compiled library."""

import sys

from kfmc import _kfmc


def main() -> int:
    """Runs ``kfmc`` with this process's arguments and exits with its exit code."""
    code = _kfmc.cli_main(sys.argv)
    sys.stdout.flush()
    sys.exit(code)
