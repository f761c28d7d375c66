"""Shared helpers for benchmark scripts: the machine line, a plain-text table printer and
the captures they read."""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import platform
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import jax

from jaxrefl.cli._compile import prefer_loop_emitters

# The benchmarks measure what the command line runs, with its XLA settings: set here, before
# any script starts JAX's backend (every script imports this module before computing).
prefer_loop_emitters()

if TYPE_CHECKING:
    from jaxrefl.io import Capture


def machine() -> str:
    """One line describing where the numbers were measured."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = ", ".join(sorted({d.platform for d in jax.devices()}))
    flags = os.environ.get("XLA_FLAGS", "")
    return (
        f"{cpu}; {os.cpu_count()} cores; jax {jax.__version__} on {dev}; "
        f"python {platform.python_version()}" + (f"; XLA_FLAGS {flags}" if flags else "")
    )


def table(headers: list[str], rows: list[list[object]]) -> str:
    """A GitHub-style Markdown table."""
    cells = [[str(c) for c in r] for r in rows]
    widths = [
        max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)
    ]

    def line(vals):
        return "| " + " | ".join(v.ljust(w) for v, w in zip(vals, widths, strict=True)) + " |"

    out = [line(headers), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += [line(r) for r in cells]
    return "\n".join(out)


def demo_capture(out: Path, size: int) -> Path:
    """Write a ``jaxrefl demo`` capture (photos only, no fit) of ``size`` x ``size`` to
    ``out`` without its printed table, which is not the calling report's. The command
    line's persistent compilation cache stays off: the benchmark's compile times are its
    own, not programs loaded from an earlier run."""
    from jaxrefl.cli import main as cli

    with contextlib.redirect_stdout(io.StringIO()):
        args = ["demo", "--out", str(out), "--size", str(size), "--no-fit"]
        rc = cli([*args, "--no-compile-cache"])
    if rc != 0:
        raise SystemExit("jaxrefl demo failed")
    return out


def shared_data() -> Path:
    """The shared data folder: ``$JAXREFL_SHARED_DATA``, else ``shared/data`` beside the
    checkout."""
    env = os.environ.get("JAXREFL_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def flash_capture(name: str, size: int) -> Capture:
    """The real flash capture ``name`` (``bath_tile``, ``yellow_box``: ``svbrdf_flash`` in
    :func:`shared_data`), read at ``size`` x ``size``."""
    from jaxrefl.io import load_capture

    return load_capture(shared_data() / "svbrdf_flash" / name, resolution=size)


def write_section(section: str, body: str) -> Path:
    """Replace (or append) one script's section of ``docs/benchmarks.md``.

    The section lies between ``<!-- section:start -->`` and ``<!-- section:end -->``
    markers, so each script rewrites its own rows and leaves the others alone.
    """
    path = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
    path.parent.mkdir(exist_ok=True)
    start, end = f"<!-- {section}:start -->", f"<!-- {section}:end -->"
    text = (
        path.read_text()
        if path.exists()
        else "# Benchmarks\n\nWritten by the scripts in `benchmarks/`.\n"
    )
    block = f"{start}\n{body}\n{end}"
    if start in text and end in text:
        head, rest = text.split(start, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text)
    return path


class _Tee(io.TextIOBase):
    """A text stream that writes to the terminal and keeps a copy."""

    def __init__(self, out):
        self.out, self.kept = out, io.StringIO()

    def write(self, s: str) -> int:
        self.out.write(s)
        return self.kept.write(s)

    def flush(self) -> None:
        self.out.flush()


def run_and_record(
    section: str, title: str, main: Callable[[], int | None], script: str | None = None
) -> int:
    """Run a benchmark's ``main``, print as usual, and record what it printed.

    The printed report becomes the script's section of ``docs/benchmarks.md``: a heading,
    the date, the machine and the command line, then the report itself (its Markdown
    headings one level down). ``--no-write`` on the command line prints only. ``script``:
    the command named in the heading (default: ``<section>.py``).
    """
    record = "--no-write" not in sys.argv
    if not record:
        sys.argv.remove("--no-write")
    tee = _Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        rc = main()
    if rc not in (None, 0) or not record:
        return int(rc or 0)
    report = "\n".join(
        "#" + line if line.startswith("#") else line for line in tee.kept.getvalue().splitlines()
    )
    args = " ".join(sys.argv[1:])
    body = (
        f"## {title} (`benchmarks/{script or section + '.py'}`)\n\n"
        f"{datetime.date.today().isoformat()}; {machine()}; "
        f"`{args or 'default arguments'}`.\n\n{report.strip()}"
    )
    print(f"wrote {write_section(section, body)}")
    return 0
