"""Shared helpers for benchmark scripts: the machine line and a plain-text table printer."""

from __future__ import annotations

import os
import platform
from pathlib import Path

import jax


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
    return (
        f"{cpu}; {os.cpu_count()} cores; jax {jax.__version__} on {dev}; "
        f"python {platform.python_version()}"
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
