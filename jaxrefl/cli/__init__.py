"""The ``jaxrefl`` command line. Subcommands live in their own modules under ``cli/``."""

from ._main import main as main
