"""One fit over two processes on localhost (JAX's distributed runtime, CPU collectives):
a process that dies leaves its tiles and stops the other at once with one line, a rerun
resumes them, and the maps equal a one-process fit's bit for bit."""

from __future__ import annotations

import json
import os
import shlex
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl.cli import main
from jaxrefl.io import load_capture, map_key, read_exr

SIZE = 8  # 64 pixels in 4 tiles of 16: two a process
TILE = 16
TIMEOUT_S = 120  # a subprocess still running after this is killed: the test fails, not hangs
# The survivor of a dead process must stop within this many seconds of the death, well
# inside JAX's heartbeat timeout (100 s, the command line's): the death is seen at the
# survivor's next barrier, after at most one more tile of its own.
SURVIVOR_S = 60

# Process 1 of the group through the library; it dies after its first tile.
_ENTRY = textwrap.dedent(
    """
    import os, sys
    import jax
    import numpy as np
    from jaxrefl import fit, svbrdf
    from jaxrefl.io import load_capture

    jax.config.update("jax_enable_x64", True)
    cap_dir, out, port = sys.argv[1:]
    dist = fit.Distributed(f"localhost:{port}", 2, 1)
    dist.initialize()  # before load_capture, which computes with JAX

    def die_after_first_tile(i, n):
        os._exit(17)  # no clean-up, like a killed process

    job = svbrdf.FitJob(model="lambert", tile_pixels=16, config=fit.FitConfig(dtype=np.float64))
    svbrdf.fit_capture(load_capture(cap_dir), job, out, on_tile=die_after_first_tile,
                       distributed=dist)
    """
)
# ``jaxrefl`` itself, in the interpreter running the tests.
_CLI = "import sys; from jaxrefl.cli import main; sys.exit(main())"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


def _env() -> dict[str, str]:
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    # One device a process, as in the reference fit, and the session's code generation
    # (tests/conftest.py): the runs are compared with it bit for bit.
    flags = os.environ.get("XLA_FLAGS", "").split()
    env["XLA_FLAGS"] = " ".join(f for f in flags if "device_count" not in f)
    return env


def _group(cmd_of_pid) -> list[subprocess.Popen]:
    return [
        subprocess.Popen(
            cmd_of_pid(pid), env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        for pid in (0, 1)
    ]


def _finish(p: subprocess.Popen, timeout: float) -> tuple[int, str]:
    try:
        out, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate()
        return -9, out
    return p.returncode, out


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--size", str(SIZE), "--no-fit", "--noise", "0"]) == 0
    return out


def test_two_processes_resume_a_dead_one_and_equal_one_process(capture_dir, tmp_path):
    out = tmp_path / "fit"
    # 1. Two processes: process 0 is the command line below; process 1 (the library, the
    #    same job) dies after its first tile (1). Process 0 fits its share (0, 2), finds at
    #    the next barrier that process 1 stopped, and ends with one line and exit status 4.
    port = _port()
    cli = [
        *("fit", str(capture_dir), "--out", str(out), "--model", "lambert"),
        *("--tile-pixels", str(TILE), "--dtype", "float64", "--no-previews", "--quiet"),
        "--keep-tiles",  # step 3 reads the tiles' theta
        *("--distributed", "--coordinator", f"localhost:{port}", "--num-processes", "2"),
    ]
    first = [*cli, "--process-id", "0"]
    procs = _group(
        lambda pid: (
            [sys.executable, "-c", _CLI, *first]
            if pid == 0
            else [sys.executable, "-c", _ENTRY, str(capture_dir), str(out), str(port)]
        )
    )
    rc1, log1 = _finish(procs[1], TIMEOUT_S)
    died = time.monotonic()
    rc0, log0 = _finish(procs[0], SURVIVOR_S)
    survived_s = time.monotonic() - died
    assert rc1 == 17, log1[-3000:]
    assert rc0 == 4, (rc0, survived_s, log0[-3000:])  # cli.EXIT_PROCESS_STOPPED
    lines = [ln for ln in log0.splitlines() if ln.startswith("jaxrefl fit: ")]
    assert len(lines) == 1 and "Traceback" not in log0, log0[-3000:]
    assert "process 1 of 2 stopped (died or was killed)" in lines[0], lines
    assert f"tiles done so far are in {out / 'tiles'}" in lines[0], lines
    assert lines[0].endswith(shlex.join(["jaxrefl", *first])), lines
    done = sorted(p.name for p in (out / "tiles").glob("tile_*.npz"))
    assert done == ["tile_00000.npz", "tile_00001.npz", "tile_00002.npz"], (done, log0[-3000:])

    # 2. A rerun of the command line with --distributed loads the three tiles and fits
    #    the missing one once (process 0's share; process 1 has none).
    port = _port()
    cli[-3] = f"localhost:{port}"
    procs = _group(lambda pid: [sys.executable, "-c", _CLI, *cli, "--process-id", str(pid)])
    results = [_finish(p, TIMEOUT_S) for p in procs]
    for rc, log in results:
        assert rc == 0, log[-3000:]
    report = json.loads((out / "report.json").read_text())
    t = report["timings"]
    assert t["tiles"] == 4 and t["tiles_loaded"] == 3, t
    assert t["processes"]["count"] == 2 and t["processes"]["tiles_computed"] == [1, 0], t

    # 3. The maps equal the one-process fit's (float64 fit; maps stored as float32).
    job = svbrdf.FitJob(model="lambert", tile_pixels=TILE, config=fit.FitConfig(dtype=np.float64))
    ref = svbrdf.fit_capture(load_capture(capture_dir), job)
    maps = {map_key(k): v for k, v in read_exr(out / "maps.exr").channels.items()}
    assert set(ref.maps) <= set(maps)
    for name, v in ref.maps.items():
        np.testing.assert_array_equal(maps[name], v, err_msg=name)
    theta = np.concatenate(
        [np.load(out / "tiles" / f"tile_{i:05d}.npz")["theta"] for i in range(4)]
    )
    np.testing.assert_array_equal(theta, ref.theta)


def test_bad_distributed_options_are_refused_by_name(capture_dir, tmp_path):
    with pytest.raises(ValueError, match="coordinator must be HOST:PORT"):
        fit.Distributed("localhost", 2, 0)
    with pytest.raises(ValueError, match=r"process_id must be in 0 \.\. num_processes - 1"):
        fit.Distributed("localhost:1234", 2, 2)
    with pytest.raises(ValueError, match="needs out_dir"):
        svbrdf.fit_capture(load_capture(capture_dir), distributed=fit.Distributed())
    args = ["fit", str(capture_dir), "--out", str(tmp_path), "--process-id", "1"]
    assert main(args) == 1  # --process-id without --distributed


def test_mcmc_chunks_on_two_devices_equal_one_device():
    """The adaptive MCMC with two forced host devices (a fresh process: the flag must
    precede JAX's start) against the same run on one device: each chunk's pixels are split
    over a 1-D mesh (``map_sharded``), padded to the device count.

    Tolerance: every pixel has its own key, so its chains take the same random steps on
    either device; only the rounding of a differently laid-out batch differs, which the
    chains carry along (float64; seen: 1e-7 in the draws), hence atol 1e-5 on every draw and
    on the map's std. A chunk or shard given the wrong pixels yields draws around another
    pixel's albedo, more than 0.05 away (MIN_GAP, checked; seen: 0.41). The sampler on the
    mesh compiles once for both chunks (traced once)."""
    code = textwrap.dedent(
        """
        import math
        import numpy as np, jax
        jax.config.update("jax_enable_x64", True)
        from jaxrefl import brdf, fit
        from jaxrefl import posterior as jp
        from jaxrefl.posterior import _hmc
        assert jax.device_count() == 2

        sigma, n, k = 0.02, 6, 6
        m = brdf.get("lambert")
        space = fit.ParamSpace(m, channels=3)
        rng = np.random.default_rng(0)
        alb = 0.1 + 0.12 * np.arange(n)[:, None] + rng.uniform(0, 0.02, (n, 3))  # apart
        wi = np.tile(np.array([0.0, 0.0, 1.0]), (n, k, 1))
        data = fit.pixel_data(alb[:, None, :] / math.pi + sigma * rng.normal(size=(n, k, 3)), wi)
        lp = jp.log_posterior(m, space, fit.GaussianNoise(sigma))
        # starts at the true albedos (no fit: one compilation less), Laplace std 0.05
        theta = np.asarray(space.from_natural({"albedo": alb}, dtype=np.float64))
        theta_std, flag = np.full_like(theta, 0.05), np.zeros(n, np.int32)
        # short chains, a diagonal metric in theta (the cheapest sampler to compile)
        hmc = jp.HMCOptions(num_warmup=20, num_samples=20, num_chains=2,
                            num_integration_steps=8, dense_mass=False, reparam="none")
        # two chunks of 3 pixels, each padded to 4 for the two devices
        o = jp.AdaptiveOptions(mcmc="all", hmc=hmc, gibbs=None, chunk=4, seed=7,
                               rerun_rhat=None, workers=1)
        args = (lp, data, theta, theta_std, flag, o)

        meshes, traced = [], []
        real, real_run = _hmc.map_sharded, _hmc._run
        def spy(fn, a, ndev):
            meshes.append(ndev)
            return real(fn, a, ndev)
        def counted(*a):
            traced.append(1)  # on the mesh: once per compilation of the sampler
            return real_run(*a)
        _hmc.map_sharded, _hmc._run = spy, counted
        two = jp.adaptive_uncertainty(*args)
        assert len(traced) == 1, traced  # both chunks run one compiled program
        _hmc.device_count = lambda devices=None: 1
        one = jp.adaptive_uncertainty(*args)
        assert meshes == [2, 2, 1, 1], meshes
        a, b = two.samples.theta, one.samples.theta
        assert a.shape == b.shape == (n, 2, 20, lp.size), (a.shape, b.shape)
        print("MAX_DIFF", float(np.max(np.abs(a - b))))
        mean = b.mean(axis=(1, 2))
        gap = np.abs(mean[:, None, :] - mean[None, :, :]).max(axis=-1)
        print("MIN_GAP", float(gap[~np.eye(n, dtype=bool)].min()))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)
        np.testing.assert_allclose(two.std, one.std, rtol=0, atol=1e-5)
        print("ok")
        """
    )
    root = str(Path(__file__).resolve().parents[1])
    env = _env()
    env["XLA_FLAGS"] += " --xla_force_host_platform_device_count=2"
    out = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        cwd=root,
        capture_output=True,
        text=True,
        timeout=600,  # generous: a shared machine slows the two compilations
    )
    assert out.returncode == 0 and "ok" in out.stdout, (out.stdout, out.stderr[-3000:])
    gap = float(out.stdout.split("MIN_GAP")[1].split()[0])
    assert gap > 0.05, out.stdout  # mis-assigned pixels would be told apart by far


def test_process_group_error_names_the_stopped_processes():
    e = fit.ProcessGroupError("jaxrefl fit: tiles written", [1, 3], 4)
    assert str(e) == (
        "processes 1, 3 of 4 stopped (died or was killed) before 'jaxrefl fit: tiles written'"
    )
    assert e.missing == [1, 3] and e.processes == 4
    lost = fit.ProcessGroupError("s", None, 2)  # the coordination service was unreachable
    assert str(lost).startswith("process 0 (the coordinator) or another process of 2 stopped")
