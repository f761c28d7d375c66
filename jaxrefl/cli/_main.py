"""Entry point: ``jaxrefl <command> [options]``."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

__all__ = ["main", "positive_int"]


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (a count, a size or a factor)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


# Command name -> module defining HELP, add_arguments(parser) and run(args) -> int.
_COMMANDS = {
    "demo": "jaxrefl.cli._demo",
    "fit": "jaxrefl.cli._fit",
    "sample": "jaxrefl.cli._sample",
    "ps": "jaxrefl.cli._ps",
    "fit-brdf": "jaxrefl.cli._fit_brdf",
    "models": "jaxrefl.cli._models",
    "export": "jaxrefl.cli._export",
}


def build_parser() -> argparse.ArgumentParser:
    from jaxrefl import __version__

    parser = argparse.ArgumentParser(
        prog="jaxrefl",
        description="Probabilistic reflectance estimation in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"jaxrefl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in _COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    from jaxrefl import brdf

    # At the command line every concrete BRDF evaluation checks its parameters' ranges and
    # its directions (brdf.set_validation): a bad value is refused by name, not rendered.
    before = brdf.set_validation(True)
    try:
        return int(args._run(args) or 0)
    except (ValueError, FileNotFoundError, KeyError) as exc:
        print(f"jaxrefl {args.command}: error: {exc}", file=sys.stderr)
        return 1
    finally:
        brdf.set_validation(before)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
