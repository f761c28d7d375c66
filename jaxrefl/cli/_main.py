"""Entry point: ``jaxrefl <command> [options]``.

Adding a subcommand
-------------------
A subcommand is a module under ``jaxrefl/cli/`` with

- a docstring (the first line a summary, then the synopsis indented by four spaces, then
  prose; shown by ``jaxrefl COMMAND --help`` with its Sphinx roles made plain),
- ``HELP``: one line for ``jaxrefl --help``,
- ``add_arguments(parser)``: every option with a ``help`` text; a default other than
  None/False is shown by the formatter, a None default is explained in the help,
- ``run(args) -> int``: the work; JAX and the library are imported here, not at module level,
- optionally ``resume_hint(args) -> str``: what to type to resume after Ctrl-C,
- optionally ``COMPILES = False`` for a command that runs no JAX program (no cache option),

and one line in :data:`COMMANDS` below. Building the parser imports these modules and
nothing else: ``jaxrefl --help`` must not import JAX (``tests/test_cli_behaviour.py``
checks). Model names come from :mod:`jaxrefl._names`, which imports nothing.

Errors
------
Argument errors exit 2 with argparse's one-line message (:func:`main` returns the status
rather than raising ``SystemExit``, so tests call it in-process). While a command runs, a bad value
(``ValueError``, ``KeyError``) or an ``OSError`` (naming its path) is one line on stderr and
exit status 1; Ctrl-C is one line and exit status 130 (128 + SIGINT, the shell convention).
In a job of several processes (``--distributed``), a process that stops (killed, out of
memory) ends the others at their next barrier with one line naming it and the command
that resumes, and exit status :data:`EXIT_PROCESS_STOPPED` (4), at once rather than after
JAX's heartbeat timeout (:func:`jaxrefl.fit.leave_group`). Exit status 3 belongs to
``jaxrefl sample``: outputs written, a convergence target missed.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jaxrefl._errors import JaxreflError

__all__ = [
    "COMMANDS",
    "EXIT_PROCESS_STOPPED",
    "build_parser",
    "finite_float",
    "fraction",
    "main",
    "non_negative_float",
    "plain",
    "positive_float",
    "positive_int",
]

#: Command name -> module (see "Adding a subcommand" above).
COMMANDS: dict[str, str] = {
    "demo": "jaxrefl.cli._demo",
    "fit": "jaxrefl.cli._fit",
    "sample": "jaxrefl.cli._sample",
    "ps": "jaxrefl.cli._ps",
    "fit-brdf": "jaxrefl.cli._fit_brdf",
    "models": "jaxrefl.cli._models",
    "export": "jaxrefl.cli._export",
    "frame": "jaxrefl.cli._frame",
    "capture": "jaxrefl.cli._capture",
    "plan": "jaxrefl.cli._plan",
}


def _int_at_least(text: str, lo: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= {lo}, not {text!r}") from None
    if value < lo:
        raise argparse.ArgumentTypeError(f"must be >= {lo}, got {value}")
    return value


def photo_indices(text: str, flag: str, example: str = "0,3,5") -> tuple[int, ...]:
    """Distinct photo indices >= 0 separated by commas, for ``flag``'s message."""
    try:
        idx = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        idx = (-1,)
    if not idx or min(idx) < 0 or len(set(idx)) != len(idx):
        raise argparse.ArgumentTypeError(
            f"{flag} takes distinct photo indices >= 0 separated by commas (e.g. {example}), "
            f"not {text!r}"
        )
    return idx


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (a count, a size or a factor)."""
    return _int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """An argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def finite_float(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, not {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, not {text!r}")
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value:g}")
    return value


def non_negative_float(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value:g}")
    return value


def fraction(text: str) -> float:
    """An argparse type: a number in [0, 1]."""
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value:g}")
    return value


_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`(~?)([^`<]*?)(?:\s*<[^>]*>)?`")


def plain(text: str) -> str:
    """Docstring text without Sphinx markup: ``:func:`~a.b.f``` -> ``f``, ``:class:`a.B```
    -> ``a.B``, double backquotes dropped."""

    def role(m: re.Match[str]) -> str:
        name = m.group(2)
        return name.rsplit(".", 1)[-1] if m.group(1) else name

    return _ROLE.sub(role, text).replace("``", "")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the docstring's layout (synopsis apart from prose) and appends each option's
    default unless it is None/False or the help already states it."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or default is None
            or default is False
            or default is argparse.SUPPRESS
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        return f"{text} (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    """The full parser; imports the subcommand modules, which import neither JAX nor the
    library at module level."""
    from jaxrefl import __version__

    parser = argparse.ArgumentParser(
        prog="jaxrefl",
        description="Probabilistic reflectance estimation in JAX.",
        epilog="jaxrefl COMMAND --help describes a command and every option.",
        formatter_class=_Formatter,
    )
    parser.add_argument("--version", action="version", version=f"jaxrefl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=plain(module.__doc__ or module.HELP),
            formatter_class=_Formatter,
        )
        module.add_arguments(p)
        if getattr(module, "COMPILES", True):
            p.add_argument(
                "--no-compile-cache",
                action="store_true",
                help="do not keep compiled programs on disk (also: JAXREFL_NO_COMPILE_CACHE=1); "
                "the cache is in $XDG_CACHE_HOME/jaxrefl/jax, or JAX_COMPILATION_CACHE_DIR",
            )
        p.set_defaults(_module=module)
    return parser


def _os_message(exc: OSError) -> str:
    """One line naming the path: ``out/maps.exr: Permission denied``."""
    if exc.filename is not None:
        where = str(exc.filename)
        if exc.filename2 is not None:
            where += f" -> {exc.filename2}"
        return f"{where}: {exc.strerror or exc}"
    return str(exc)


# Exit status of a process whose peer in a --distributed job stopped (module docstring);
# distinct from 3, which ``jaxrefl sample`` returns for draws that missed a convergence target.
EXIT_PROCESS_STOPPED = 4


def _process_stopped(name: str, exc: RuntimeError, module: Any, args, argv) -> None:
    """One line and an immediate exit where ``exc`` is a stopped peer; else nothing."""
    from jaxrefl.fit import ProcessGroupError, leave_group

    if not isinstance(exc, ProcessGroupError):
        return
    hint = getattr(module, "resume_hint", None)
    where = (
        hint(args).split(";")[0] if hint is not None else f"the work done so far is in {args.out}"
    )
    command = shlex.join(["jaxrefl", *(sys.argv[1:] if argv is None else argv)])
    print(
        f"{name}: {exc}; {where}; resume on every process (any number of them) with: {command}",
        file=sys.stderr,
    )
    leave_group(EXIT_PROCESS_STOPPED)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``jaxrefl`` with ``argv`` (default: ``sys.argv[1:]``); the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) or an argument error (2, one line)
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    module: Any = args._module
    name = f"jaxrefl {args.command}"
    clock = None
    try:
        if getattr(module, "COMPILES", True):
            from ._compile import CompileClock, enable_compile_cache, prefer_loop_emitters

            prefer_loop_emitters()
            cache = enable_compile_cache(off=args.no_compile_cache)
            clock = CompileClock().start()
        from jaxrefl import brdf

        # At the command line every concrete BRDF evaluation checks its parameters' ranges
        # and its directions (brdf.set_validation): a bad value is refused by name.
        before = brdf.set_validation(True)
        try:
            status = int(module.run(args) or 0)
        finally:
            brdf.set_validation(before)
        if clock is not None:
            print(clock.line(cache))
        return status
    except KeyboardInterrupt:
        hint = getattr(module, "resume_hint", None)
        more = f"; {hint(args)}" if hint is not None else ""
        print(f"{name}: interrupted{more}", file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"{name}: error: {_os_message(exc)}", file=sys.stderr)
        return 1
    except (ValueError, KeyError) as exc:
        text = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"{name}: error: {text}", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        _process_stopped(name, exc, module, args, argv)
        raise
    finally:
        if clock is not None:
            clock.stop()


def check_out_dir(path: Path, flag: str = "--out") -> Path:
    """``path`` as an output folder, checked before any work: refused (one line) when it, or
    the nearest part of it that exists, is a file or a folder this user cannot write to."""
    for part in (path, *path.parents):
        if not part.exists():
            continue
        if not part.is_dir():
            what = "exists" if part == path else f"is inside {part}, which exists"
            raise JaxreflError(f"{flag} {path}: {what} and is not a folder; name a folder")
        if not os.access(part, os.W_OK | os.X_OK):
            raise JaxreflError(f"{flag} {path}: {part} is not writable")
        break
    return path


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
