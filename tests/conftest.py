"""Shared test configuration.

* float64 is enabled for the whole session (tests that check float32 ask for it explicitly
  with ``dtype=jnp.float32``), and implicit rank promotion is an error.
* The JAX persistent compilation cache is on for the run (``.pytest_cache/jax-compilation``,
  or ``JAXREFL_TEST_JAX_CACHE``; ``off`` disables it). Many tests compile the same solver on
  the same shapes in different processes (xdist workers, notebook kernels, CLI subprocesses);
  the cache compiles each once. It is set through the environment so subprocesses inherit it,
  and the command line (``jaxrefl/cli/_compile.py``) uses it rather than the user's folder.
* XLA compiles the tests' programs with its CPU loop emitters
  (``--xla_cpu_use_fusion_emitters=false`` in ``XLA_FLAGS``, unless set) and without LLVM's
  optimisations (``--xla_backend_optimization_level=0``): see below.
* ``shared_data`` locates ``../shared/data`` through ``JAXREFL_SHARED_DATA``. In CI
  (``CI`` set, as ``.ci/run`` does) a missing data folder is a failure, never a skip.
* Every ``report.json`` a test leaves under its ``tmp_path`` must parse as strict JSON (no
  ``NaN`` or ``Infinity`` tokens; ``jaxrefl._jsonsafe``): checked after the test, an error of
  that test otherwise. ``strict_json`` is the parser.
* ``--compile-report N`` lists the N tests that spent the most seconds in XLA's compiler,
  with the run's totals (most of the suite's time is compiling: the place to look first
  when the suite grows slow).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import jax
import pytest

# ArviZ writes a once-a-day stamp into the user's cache folder when it is first imported,
# through a fixed temporary file name: two test workers importing it at once on a fresh
# machine race on that file (FileNotFoundError at collection). Imported here, in the process
# that starts the workers, it writes the stamp once before they exist.
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import arviz  # noqa: F401

from jaxrefl.cli._compile import prefer_loop_emitters

_cache = os.environ.get(
    "JAXREFL_TEST_JAX_CACHE",
    str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax-compilation"),
)
if _cache != "off":
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    # Programs that took 0.1 s or more to compile are kept: without LLVM's optimisations
    # (below) many of the suite's programs compile in well under a second, and a higher
    # threshold would have every worker and subprocess compile them again.
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs",
        float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
    )
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
else:
    # The command line would otherwise keep its programs in the user's cache folder.
    os.environ.setdefault("JAXREFL_NO_COMPILE_CACHE", "1")

# XLA's CPU backend generates the tests' programs with its loop emitters rather than its
# newer fusion emitters (``--xla_cpu_use_fusion_emitters=false``): most of the suite's time
# is compiling programs that then run once on a few pixels, and the loop emitters compile
# them in about two thirds of the time while they run about as fast. Both generate the same
# IEEE arithmetic (a GGX model's values and gradients agree bit for bit, float32 and
# float64), so the tests check the same numbers. Set before the backend starts, in the
# environment so that subprocesses (the command line, notebook kernels) inherit it; a
# value the user set is kept.
prefer_loop_emitters()

# XLA's CPU backend also hands the tests' programs to LLVM without optimising them
# (``--xla_backend_optimization_level=0``, unless set): XLA's own graph optimisations
# still run, only LLVM's are skipped. Most of the suite's time is compiling, LLVM's passes
# are most of that, and the programs, most of them run once on a few pixels, run only
# somewhat slower without them. Unlike the choice of emitters, this changes the machine
# code's rounding (no fused multiply-adds, among others): results can differ from an
# optimised build's in the last bits. The tests compare with tolerances, and the few that
# compare bit for bit (a resumed or distributed run against one process) run both sides
# with these flags. In the environment, for the subprocesses; a value the user set is kept.
_LLVM_O0 = "--xla_backend_optimization_level=0"
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_LLVM_O0}".strip()

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

try:
    from hypothesis import HealthCheck, settings

    settings.register_profile(
        "ci",
        max_examples=60,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
        derandomize=True,
    )
    settings.register_profile("dev", max_examples=30, deadline=None)
    settings.load_profile("ci" if os.environ.get("CI") else "dev")
except ImportError:  # hypothesis is a test extra
    pass


def _shared_data_dir() -> Path:
    """$JAXREFL_SHARED_DATA, else shared/data beside the checkout (it may not exist)."""
    env = os.environ.get("JAXREFL_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = _shared_data_dir()
    if not d.is_dir():
        where = "JAXREFL_SHARED_DATA" if os.environ.get("JAXREFL_SHARED_DATA") else "no env var"
        msg = (
            f"shared data not found at {d} ({where}): set JAXREFL_SHARED_DATA to the shared/data"
            " folder, or put it beside the checkout"
        )
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return d


def strict_json_loads(text: str):
    """``json.loads`` that refuses the non-standard tokens NaN, Infinity and -Infinity."""

    def refuse(token: str):
        raise ValueError(f"non-standard token {token}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture
def strict_json():
    return strict_json_loads


# A worker process keeps every program it compiled (JAX's in-memory caches) for the whole
# run: past this resident size, a test module's end frees them (later modules compile what
# they need again, or read it from the persistent cache), so that a long run's worker does
# not run out of memory inside XLA's compiler.
_RSS_LIMIT_BYTES = 5 * 2**30


def _rss_bytes() -> int:
    """The process's resident size (Linux: /proc/self/statm; 0 elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return 0
    return pages * os.sysconf("SC_PAGE_SIZE")


@pytest.fixture(autouse=True, scope="module")
def _bounded_compile_memory():
    yield
    if _rss_bytes() > _RSS_LIMIT_BYTES:
        import gc

        jax.clear_caches()
        gc.collect()


@pytest.fixture(autouse=True)
def _reports_are_strict_json(request):
    yield
    tmp = getattr(request.node, "funcargs", {}).get("tmp_path")
    if tmp is None:
        return
    for path in sorted(Path(tmp).rglob("report.json")):
        try:
            strict_json_loads(path.read_text())
        except ValueError as e:
            pytest.fail(f"{path} is not strict JSON ({e})", pytrace=False)


# ---------------------------------------------------------------------------- compile report
# ``--compile-report N``: after the run, the N tests (setup, call and teardown together) that
# spent the most seconds in XLA's compiler, from JAX's monitoring events, and the run's total
# beside the tests' own time: where the suite's time goes, since most of it is compiling.
# Each phase's seconds travel in its report's ``user_properties``, so xdist workers' figures
# reach the controller, which sums and prints them.
_COMPILE_EVENTS = {
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
}
_compile_s = {"compile": 0.0, "lower": 0.0, "programs": 0}
_compile_rows: dict[str, list[float]] = {}


def pytest_addoption(parser):
    parser.addoption(
        "--compile-report",
        type=int,
        default=0,
        metavar="N",
        help="list the N tests that spent the most seconds compiling (XLA), with totals",
    )


def _on_compile_event(event: str, duration: float, **_kw) -> None:
    kind = _COMPILE_EVENTS.get(event)
    if kind is not None:
        _compile_s[kind] += duration
        _compile_s["programs"] += kind == "compile"


def pytest_configure(config):
    if config.getoption("--compile-report", 0):
        jax.monitoring.register_event_duration_secs_listener(_on_compile_event)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    if item.config.getoption("--compile-report", 0):
        taken = (_compile_s["compile"], _compile_s["lower"], _compile_s["programs"])
        outcome.get_result().user_properties.append(("jax_compile", taken))
        _compile_s.update(compile=0.0, lower=0.0, programs=0)


def pytest_runtest_logreport(report):
    for key, value in report.user_properties:
        if key != "jax_compile":
            continue
        comp, lower, programs = value
        row = _compile_rows.setdefault(report.nodeid, [0.0, 0.0, 0.0, 0])
        row[0] += report.duration
        row[1] += comp
        row[2] += lower
        row[3] += programs


def pytest_terminal_summary(terminalreporter, config):
    n = config.getoption("--compile-report", 0)
    if not n or not _compile_rows:
        return
    rows = sorted(_compile_rows.items(), key=lambda kv: -kv[1][1])
    total = [sum(r[i] for _, r in rows) for i in range(4)]
    tr = terminalreporter
    tr.section("XLA compile time per test")
    tr.write_line(
        f"all tests: {total[0]:.0f} s, of which XLA compile {total[1]:.0f} s and lowering "
        f"{total[2]:.0f} s ({int(total[3])} programs compiled or loaded from the persistent "
        "cache: a load counts with its own, shorter time)"
    )
    for nodeid, (dur, comp, lower, programs) in rows[:n]:
        tr.write_line(
            f"{comp:7.1f} s compile {lower:6.1f} s lower {dur:7.1f} s test "
            f"{int(programs):5d} programs  {nodeid}"
        )
