"""Scale-out: one job in 1 and in 2 processes (JAX's distributed runtime) on this machine.

    python benchmarks/scale_out.py [--fit-size 512] [--post-size 128] [--processes 1,2]
                                   [--model ggx] [--no-write]

Two jobs on the procedural demo capture (``jaxrefl demo``: 9 flash photos, 8-bit):

* the fit (:func:`jaxrefl.svbrdf.fit_capture`, ``--model``, float32, tiles of 4096
  pixels) of a ``--fit-size`` square capture;
* the adaptive uncertainty map (:func:`jaxrefl.svbrdf.uncertainty_maps`: the float64 fit,
  Laplace, then MCMC with :data:`jaxrefl.posterior.UNCERTAINTY_MAP_HMC` on the flagged pixels and
  a 2% audit, no second pass; ``--warmup`` / ``--samples`` shorten its chains) of a
  ``--post-size`` square capture, its MCMC pixels in chunks of ``--chunk`` (the chunks are
  what the processes share); ``--post-rows R`` maps the first R rows of that capture only.

Each job runs as N processes on localhost (N = 1: a plain run; N > 1: ``--distributed``
with a coordinator on a free local port), each a fresh interpreter started from the same
command, sharing one output folder. ``wall s`` is from starting the processes to the last
one's exit (interpreter start, JAX start, compilation, work, outputs); ``work s`` is the
slowest process's time in the work itself (the fit's tiles, or fit + MCMC), compilation
apart (``compile s``: the fit's, the slowest process's; the MCMC sampler's, the first
chunk's time minus the median of the others', shown only where every process ran two
chunks or more). Speed-up is the 1-process time over the
N-process time; efficiency is speed-up / N. ``CPU s per process`` is each process's user +
system time over all its threads (``os.wait4``): with one process XLA already runs its
operations on several threads, so on a machine of few cores two processes mostly share the
same cores. The 1-minute load average, sampled every second while the processes run (mean /
max), says how busy the machine was: it may be shared with other work, which makes every
figure slower and the speed-ups smaller.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import demo_capture, run_and_record, table  # noqa: E402

ROOT = HERE.parent

# One process of a job: the library through a small entry (the same as the command line).
_FIT = """
import sys
from jaxrefl import fit, svbrdf
from jaxrefl.io import load_capture

cap_dir, out, model, coord, n, pid = sys.argv[1:]
dist = None if coord == "-" else fit.Distributed(coord, int(n), int(pid))
if dist is not None:
    dist.initialize()  # before load_capture computes with JAX
cap = load_capture(cap_dir)
res = svbrdf.fit_capture(cap, svbrdf.FitJob(model=model), out, distributed=dist)
if dist is None or dist.is_main:
    svbrdf.write_outputs(res, cap, out, previews=False)
"""

_POST = """
import dataclasses, json, sys, time
import jax
import numpy as np
from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.io import load_capture

jax.config.update("jax_enable_x64", True)
cap_dir, out, model, coord, n, pid, chunk, rows, warmup, samples = sys.argv[1:]
dist = None if coord == "-" else fit.Distributed(coord, int(n), int(pid))
if dist is not None:
    dist.initialize()
hmc = dataclasses.replace(jp.UNCERTAINTY_MAP_HMC, num_warmup=int(warmup), num_samples=int(samples))
opts = jp.AdaptiveOptions(hmc=hmc, rerun_rhat=None, chunk=int(chunk),
                          keep_samples=False)
job = svbrdf.FitJob(model=model, config=fit.FitConfig(dtype=np.float64))
cap = load_capture(cap_dir)
cap = cap.crop(0, int(rows), 0, cap.shape[2])
res = svbrdf.uncertainty_maps(cap, job, opts, out_dir=out, distributed=dist)
if dist is None or dist.is_main:
    svbrdf.write_uncertainty(res, out)
    (__import__("pathlib").Path(out) / "timings.json").write_text(json.dumps(
        {**res.timings, **res.map.timings, "method_counts": res.map.method_counts()}))
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


def _run_group(code: str, args: list[str], n: int, timeout: float) -> dict:
    """Start ``n`` processes of ``code`` and wait for them: wall seconds, each process's CPU
    seconds (user + system, all its threads, from ``os.wait4``) and the 1-minute load
    average sampled every second while they run."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.pop("XLA_FLAGS", None)
    coord = "-" if n == 1 else f"localhost:{_port()}"
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as logdir:
        logs = [Path(logdir) / f"process{pid}.log" for pid in range(n)]
        t0 = time.perf_counter()
        procs = []
        for pid in range(n):
            with logs[pid].open("w") as fh:  # a file, not a pipe: nothing to drain while waiting
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-c", code, *args[:3], coord, str(n), str(pid), *args[3:]],
                        env=env,
                        stdout=fh,
                        stderr=subprocess.STDOUT,
                    )
                )
        cpu: dict[int, float] = {}
        while len(cpu) < n:
            for pid, p in enumerate(procs):
                if pid in cpu:
                    continue
                done, status, ru = os.wait4(p.pid, os.WNOHANG)
                if done == 0:
                    continue
                p.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
                cpu[pid] = ru.ru_utime + ru.ru_stime
                if p.returncode != 0:
                    for q in procs:
                        if q.returncode is None:
                            q.kill()
                    raise SystemExit(
                        f"process {pid} failed ({p.returncode}):\n{logs[pid].read_text()[-3000:]}"
                    )
            if time.perf_counter() - t0 > timeout:
                for q in procs:
                    if q.returncode is None:
                        q.kill()
                raise SystemExit(f"a process ran past {timeout:.0f} s")
            time.sleep(1.0)
            loads.append(os.getloadavg()[0])
        wall = time.perf_counter() - t0
    return {"wall": wall, "cpu": [cpu[pid] for pid in range(n)], "loads": loads}


def _demo(folder: Path, size: int) -> Path:
    return demo_capture(folder / f"demo{size}", size)


def _rows(name: str, runs: dict[int, dict]) -> list[list[object]]:
    base = runs[min(runs)]
    rows = []
    for n, r in sorted(runs.items()):
        rows.append(
            [
                name,
                n,
                f"{r['wall']:.1f}",
                f"{r['work']:.1f}",
                "-" if r["compile"] is None else f"{r['compile']:.1f}",
                " / ".join(f"{c:.0f}" for c in r["cpu"]),
                f"{base['wall'] / r['wall']:.2f}",
                f"{base['wall'] / r['wall'] / n:.2f}",
                f"{base['work'] / r['work']:.2f}",
                f"{base['work'] / r['work'] / n:.2f}",
                f"{sum(r['loads']) / len(r['loads']):.1f} / {max(r['loads']):.1f}",
            ]
        )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit-size", type=int, default=512)
    ap.add_argument("--post-size", type=int, default=128)
    ap.add_argument("--processes", default="1,2")
    ap.add_argument("--model", default="ggx")
    ap.add_argument("--chunk", type=int, default=512, help="MCMC pixels per chunk")
    ap.add_argument(
        "--warmup", type=int, default=None, help="MCMC warm-up steps (default: the map's)"
    )
    ap.add_argument(
        "--samples", type=int, default=None, help="MCMC kept steps (default: the map's)"
    )
    ap.add_argument(
        "--post-rows", type=int, default=None, help="the uncertainty map of the first rows only"
    )
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    a = ap.parse_args()
    counts = [int(v) for v in a.processes.split(",")]
    a.post_rows = a.post_size if a.post_rows is None else min(a.post_rows, a.post_size)
    from jaxrefl.posterior import UNCERTAINTY_MAP_HMC

    a.warmup = UNCERTAINTY_MAP_HMC.num_warmup if a.warmup is None else a.warmup
    a.samples = UNCERTAINTY_MAP_HMC.num_samples if a.samples is None else a.samples
    tmp = Path(tempfile.mkdtemp(prefix="scale_out_"))
    try:
        fit_cap, post_cap = _demo(tmp, a.fit_size), _demo(tmp, a.post_size)
        fits, posts = {}, {}
        for n in counts:
            out = tmp / f"fit{n}"
            r = _run_group(_FIT, [str(fit_cap), str(out), a.model], n, a.timeout)
            t = json.loads((out / "report.json").read_text())["timings"]
            r.update(work=t["run_s"], compile=t["compile_s"])
            fits[n] = r
        for n in counts:
            out = tmp / f"post{n}"
            args = [str(post_cap), str(out), a.model]
            extra = [str(a.chunk), str(a.post_rows), str(a.warmup), str(a.samples)]
            r = _run_group(_POST, [*args, *extra], n, a.timeout)
            t = json.loads((out / "timings.json").read_text())
            # the sampler's compilation: the first chunk's time minus the others' (process 0's
            # chunks); unmeasured where no process ran two chunks
            r.update(work=t["fit_s"] + t["posterior_s"], compile=None)
            if t["mcmc_chunks"] >= 2 * n:
                r["compile"] = t.get("mcmc_compile_s")
            r["mcmc_pixels"], r["chunks"] = t["mcmc_pixels"], t["mcmc_chunks"]
            posts[n] = r
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    head = [
        "job",
        "processes",
        "wall s",
        "work s",
        "compile s",
        "CPU s per process",
        "speed-up (wall)",
        "efficiency (wall)",
        "speed-up (work)",
        "efficiency (work)",
        "load 1 min (mean / max)",
    ]
    rows = _rows(f"fit {a.fit_size} x {a.fit_size} ({a.model})", fits)
    crop = "" if a.post_rows == a.post_size else f", rows 0-{a.post_rows - 1}"
    rows += _rows(f"uncertainty {a.post_size} x {a.post_size}{crop} ({a.model})", posts)
    print(table(head, rows))
    p = posts[min(posts)]
    short = ""
    if (a.warmup, a.samples) != (UNCERTAINTY_MAP_HMC.num_warmup, UNCERTAINTY_MAP_HMC.num_samples):
        full = UNCERTAINTY_MAP_HMC.num_warmup + UNCERTAINTY_MAP_HMC.num_samples
        short = (
            f"; UNCERTAINTY_MAP_HMC itself runs {UNCERTAINTY_MAP_HMC.num_warmup} and "
            f"{UNCERTAINTY_MAP_HMC.num_samples}, about {full / (a.warmup + a.samples):.1f}x "
            "the MCMC time"
        )
    print(
        f"\nThe uncertainty map samples {p['mcmc_pixels']} pixels in {p['chunks']} chunks "
        f"(UNCERTAINTY_MAP_HMC with {a.warmup} warm-up and {a.samples} kept steps, no second "
        f"pass{short}). This machine has {os.cpu_count()} cores and is "
        "shared: other work ran beside these runs wherever the load average exceeds the "
        "processes' own (about the cores they keep busy), and slowed them."
    )
    print(
        "\nOn GPUs: each process owns one GPU (or one host's GPUs, meshed per process), so "
        "processes do not share compute as they share these cores; a tile or chunk is then "
        "a wide batch on one device, and the work time falls about as 1 / processes while "
        "each process has several tiles or chunks. The fixed costs (interpreter and JAX "
        "start, compilation) are paid once per process and in parallel, and bound the "
        "speed-up of a small job. Here two processes compile at once on two shared cores, "
        "which is why the 2-process compile time is longer than the 1-process one."
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("scale_out", "Scale-out over processes", main))
