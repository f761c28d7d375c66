"""JAX's persistent compilation cache for the command line, and the time spent compiling.

Every command that runs JAX compiles its programs (XLA) before it computes anything, which
is much of a small job's time (``docs/benchmarks.md``). The compiled programs are kept on
disk by JAX's persistent compilation cache, so a second identical run loads them instead:

- on by default, in ``$XDG_CACHE_HOME/jaxrefl/jax`` (``~/.cache/jaxrefl/jax`` when
  ``XDG_CACHE_HOME`` is unset);
- ``JAX_COMPILATION_CACHE_DIR``, when set, is JAX's own setting and is used as it is
  (so is ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``; otherwise every program is kept);
- ``--no-compile-cache`` or ``JAXREFL_NO_COMPILE_CACHE=1`` turn it off.

:class:`CompileClock` adds up JAX's own compile-duration events (``jax.monitoring``:
tracing, lowering and XLA compilation, or loading from the cache) and counts cache hits,
for the one ``compiling ...`` line each command prints.

:func:`prefer_loop_emitters` has XLA's CPU backend generate the command's programs with its
loop emitters (:data:`LOOP_EMITTERS` in ``XLA_FLAGS``) rather than its newer fusion
emitters, because they compile the commands' programs in less time with the same IEEE
arithmetic (``docs/benchmarks.md`` records the setting of each run). A value of that option
the user set in ``XLA_FLAGS`` is kept; GPU backends ignore it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = [
    "ENV_OFF",
    "CompileClock",
    "cache_dir",
    "chosen_cache_dir",
    "enable_compile_cache",
    "prefer_loop_emitters",
]

#: Environment variable that turns the cache off (any value but "", "0").
ENV_OFF = "JAXREFL_NO_COMPILE_CACHE"

# jax.monitoring events whose durations make up the time to compile a program.
_COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)
_HIT = "/jax/compilation_cache/cache_hits"
_MISS = "/jax/compilation_cache/cache_misses"


#: The XLA option :func:`prefer_loop_emitters` sets.
LOOP_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def prefer_loop_emitters() -> bool:
    """Add :data:`LOOP_EMITTERS` to ``XLA_FLAGS`` (module docstring) unless the user set the
    option; whether it is in effect. XLA reads the variable when JAX starts its backends,
    so this must run before the first computation (the command line calls it first)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {LOOP_EMITTERS}".strip()
    return LOOP_EMITTERS in os.environ["XLA_FLAGS"].split()


def cache_dir() -> Path:
    """Where the CLI keeps compiled programs (module docstring)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxrefl" / "jax"


def chosen_cache_dir(off: bool = False) -> Path | None:
    """The folder the cache should use (module docstring), or None when it is off; reads the
    environment only."""
    if off or os.environ.get(ENV_OFF, "") not in ("", "0"):
        return None
    preset = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    return Path(preset) if preset else cache_dir()


def enable_compile_cache(off: bool = False) -> Path | None:
    """Turn on JAX's persistent compilation cache in :func:`chosen_cache_dir`; the folder in
    use, or None. A folder that cannot be created is reported on stderr and the run goes on
    without the cache."""
    path = chosen_cache_dir(off)
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"jaxrefl: compile cache off: cannot create {path} ({exc.strerror})", file=sys.stderr)
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every program is kept, not only those over JAX's default minimum compile time: a fit's
    # many small programs add up to most of its start-up. JAX's own environment variable,
    # when set, decides.
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


class CompileClock:
    """Seconds spent compiling (JAX's compile-duration events) and persistent-cache hits,
    between :meth:`start` and :meth:`stop`."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.programs = 0
        self.hits = 0
        self.misses = 0
        self._on = False

    def _duration(self, event: str, duration_secs: float, **_: str | int) -> None:
        if self._on and event in _COMPILE_EVENTS:
            self.seconds += float(duration_secs)
            self.programs += event == _COMPILE_EVENTS[-1]

    def _event(self, event: str, **_: str | int) -> None:
        if self._on:
            self.hits += event == _HIT
            self.misses += event == _MISS

    def start(self) -> CompileClock:
        import jax.monitoring

        self._on = True
        jax.monitoring.register_event_duration_secs_listener(self._duration)
        jax.monitoring.register_event_listener(self._event)
        return self

    def stop(self) -> None:
        from jax._src import monitoring  # the public module has no unregister

        self._on = False
        try:
            monitoring.unregister_event_duration_listener(self._duration)
            monitoring.unregister_event_listener(self._event)
        except (AssertionError, ValueError):  # already gone
            pass

    def line(self, cache: Path | None) -> str:
        """``compiling: 24.1 s (312 programs; 290 loaded from the cache in DIR)``."""
        where = (
            f"{self.hits} loaded from the cache in {cache}"
            if cache is not None
            else "persistent cache off"
        )
        return f"compiling: {self.seconds:.1f} s ({self.programs} programs; {where})"
