"""How long the command line takes to answer: ``--help``, and ``jaxrefl demo`` run twice.

* ``--help``: wall time of ``python -m jaxrefl.cli --help`` (and of ``fit --help``) in a
  fresh process, median of ``--repeats`` runs, beside ``python -c "import jax"`` for
  scale. The parser is built without importing JAX.
* ``jaxrefl demo`` twice in a row, in fresh processes, with the persistent compilation cache
  in a new temporary folder (``XDG_CACHE_HOME``; ``JAX_COMPILATION_CACHE_DIR`` unset): the
  first run compiles every program and stores it, the second loads them. For each: the
  wall time, the time until the fit starts (its ``fitting ...`` line), the CLI's
  ``compiling: ...`` line (tracing, lowering and compiling or loading, summed from JAX's
  compile-duration events) and the fit's own compile and run times (``report.json``).

    python benchmarks/cli_startup.py [--size 128] [--repeats 5] [--no-write]

It prints the tables and writes them, dated and with the machine, to the section
``cli_startup`` of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _common import run_and_record, table  # noqa: E402


def _env(cache_home: Path | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    for k in ("JAX_COMPILATION_CACHE_DIR", "JAXREFL_NO_COMPILE_CACHE"):
        env.pop(k, None)
    if cache_home is not None:
        env["XDG_CACHE_HOME"] = str(cache_home)
    return env


def _wall(cmd: list[str], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(cmd, env=_env(), capture_output=True, check=True, cwd=ROOT)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _demo(out: Path, size: int, cache_home: Path) -> dict:
    """One ``jaxrefl demo`` in a fresh process: wall time, time to its ``fitting`` line,
    the CLI's compile line and the fit's report timings."""
    cmd = [sys.executable, "-m", "jaxrefl.cli", "demo", "--out", str(out), "--size", str(size)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd,
        env=_env(cache_home),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert proc.stdout is not None
    t_fit = None
    compiling = ""
    for line in proc.stdout:
        if line.startswith("fitting ") and t_fit is None:
            t_fit = time.perf_counter() - t0
        if line.startswith("compiling: "):
            compiling = line.strip()
    if proc.wait() != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed with status {proc.returncode}")
    wall = time.perf_counter() - t0
    m = re.match(r"compiling: ([\d.]+) s \((\d+) programs; (\d+) loaded", compiling)
    report = json.loads((out / "fit" / "report.json").read_text())
    t = report["timings"]
    return {
        "wall": wall,
        "to_fit": t_fit,
        "compile": float(m.group(1)) if m else float("nan"),
        "programs": int(m.group(2)) if m else 0,
        "hits": int(m.group(3)) if m else 0,
        "fit_compile": t["compile_s"],
        "fit_run": t["run_s"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128, help="demo image side (default 128)")
    ap.add_argument("--repeats", type=int, default=5, help="--help runs (median)")
    args = ap.parse_args()

    py = sys.executable
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"Load average at the start (1, 5, 15 min): {load}; other processes share the cores.\n")
    rows = [
        ["jaxrefl --help", f"{_wall([py, '-m', 'jaxrefl.cli', '--help'], args.repeats):.2f}"],
        [
            "jaxrefl fit --help",
            f"{_wall([py, '-m', 'jaxrefl.cli', 'fit', '--help'], args.repeats):.2f}",
        ],
        ['python -c "import jax" (for scale)', f"{_wall([py, '-c', 'import jax'], 3):.2f}"],
    ]
    print(f"### Help (fresh process, median of {args.repeats})\n")
    print(table(["command", "wall s"], rows))

    with tempfile.TemporaryDirectory() as tmp:
        cache_home = Path(tmp) / "cache"
        runs = [_demo(Path(tmp) / f"demo{i}", args.size, cache_home) for i in (1, 2)]
        cache_mb = sum(f.stat().st_size for f in cache_home.rglob("*") if f.is_file()) / 1e6
    print(f"\n### `jaxrefl demo --size {args.size}`, twice, fresh persistent cache\n")
    print(
        table(
            [
                "run",
                "wall s",
                "until fitting s",
                "compiling s (CLI line)",
                "programs (from cache)",
                "fit: compile s",
                "fit: run s",
            ],
            [
                [
                    name,
                    f"{r['wall']:.1f}",
                    f"{r['to_fit']:.1f}",
                    f"{r['compile']:.1f}",
                    f"{r['programs']} ({r['hits']})",
                    f"{r['fit_compile']:.1f}",
                    f"{r['fit_run']:.1f}",
                ]
                for name, r in zip(("first (empty cache)", "second"), runs, strict=True)
            ],
        )
    )
    print(
        f"\nCache after both runs: {cache_mb:.1f} MB. 'until fitting': from the start of the "
        "process to the demo's `fitting ...` line (imports, rendering the photos, writing and "
        "reading them back); the fit's compile time is then apart from its run time."
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("cli_startup", "Command-line start-up and compile cache", main))
