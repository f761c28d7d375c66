"""Shared test configuration.

* float64 is enabled for the whole session (tests that check float32 ask for it explicitly
  with ``dtype=jnp.float32``), and implicit rank promotion is an error.
* The JAX persistent compilation cache is on for the run (``.pytest_cache/jax-compilation``,
  or ``JAXREFL_TEST_JAX_CACHE``; ``off`` disables it). Many tests compile the same solver on
  the same shapes in different processes (xdist workers, notebook kernels, CLI subprocesses);
  the cache compiles each once. It is set through the environment so subprocesses inherit it,
  and the command line (``jaxrefl/cli/_compile.py``) uses it rather than the user's folder.
* ``shared_data`` locates ``../shared/data`` through ``JAXREFL_SHARED_DATA``. In CI
  (``CI`` set, as ``.ci/run`` does) a missing data folder is a failure, never a skip.
* Every ``report.json`` a test leaves under its ``tmp_path`` must parse as strict JSON (no
  ``NaN`` or ``Infinity`` tokens; ``jaxrefl._jsonsafe``): checked after the test, an error of
  that test otherwise. ``strict_json`` is the parser.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import pytest

_cache = os.environ.get(
    "JAXREFL_TEST_JAX_CACHE",
    str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax-compilation"),
)
if _cache != "off":
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
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
