"""Shared helpers for benchmark scripts: the machine line and a plain-text table printer."""

from __future__ import annotations

import os
import platform

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
