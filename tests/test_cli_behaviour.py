"""The command line as a user meets it: help text, model names, argument errors, OSErrors,
Ctrl-C, the compile cache and ``--keep-tiles``. In-process (``main`` returns the exit status)
except the one subprocess that checks ``--help`` imports no JAX."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxrefl.cli import main
from jaxrefl.cli._main import COMMANDS, build_parser, plain

ROOT = Path(__file__).resolve().parents[1]


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


# ------------------------------------------------------------------------------- help
def test_help_imports_no_jax():
    """``jaxrefl --help`` and a subcommand's help build the parser without importing JAX
    (benchmarks/cli_startup.py times it)."""
    code = (
        "import sys\n"
        "from jaxrefl.cli import main\n"
        "assert main(['--help']) == 0\n"
        "assert main(['fit', '--help']) == 0\n"
        "print('JAX LOADED' if 'jax' in sys.modules else 'no jax')\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == "no jax"


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_option_has_help_and_its_default(command):
    p = _subparsers()[command]
    text = p.format_help()
    for action in p._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        name = "/".join(action.option_strings) or action.dest
        assert action.help and action.help.strip(), f"{command} {name}: no help text"
        shown = p._get_formatter()._expand_help(action) if action.help else ""
        if action.option_strings and action.default not in (None, False):
            assert "default" in shown, f"{command} {name}: default {action.default!r} not shown"
        if action.option_strings and action.default is None and not action.required:
            # a None default means "something else decides": the help says what
            assert "default" in shown, f"{command} {name}: what happens when not given?"
    # no Sphinx markup, and the synopsis stands apart from the prose
    assert ":func:" not in text and ":class:" not in text and "``" not in text
    doc = plain(p.description or "")
    synopsis = [ln for ln in doc.splitlines() if ln.startswith(f"    jaxrefl {command}")]
    if command != "models" or synopsis:
        assert synopsis, f"{command}: no synopsis line"
        assert f"\n\n    jaxrefl {command}" in text, f"{command}: synopsis runs into the prose"


def test_plain_removes_sphinx_roles():
    text = "see :func:`~jaxrefl.io.load_capture` and :class:`jaxrefl.fit.LMOptions`, ``x``"
    assert plain(text) == "see load_capture and jaxrefl.fit.LMOptions, x"


def test_fit_help_lists_every_capture_model():
    from jaxrefl.svbrdf import CAPTURE_MODELS

    text = _subparsers()["fit"].format_help()
    for name in CAPTURE_MODELS:
        assert name in text
    assert "ggx_normal" in text


# ------------------------------------------------------------------------------- names
def test_one_model_naming_scheme():
    from jaxrefl import measured, svbrdf
    from jaxrefl._names import CAPTURE_MODELS, MEASURED_MODELS
    from jaxrefl.cli._fit_brdf import _model_names

    assert svbrdf.CAPTURE_MODELS is CAPTURE_MODELS
    assert measured.MODEL_NAMES == tuple(MEASURED_MODELS)
    assert set(measured.DEFAULT_MODELS) < set(MEASURED_MODELS)
    subs = _subparsers()
    args = subs["fit"].parse_args(["cap", "--out", "o", "--model", "Cook_Torrance_GGX"])
    assert args.model == "ggx"
    args = subs["sample"].parse_args(["f", "--out", "o", "--brdf-model", "cook_torrance_ggx"])
    assert args.brdf_model == "ggx"
    assert _model_names(["cook_torrance_beckmann,lambert", "ggx"]) == ["beckmann", "lambert", "ggx"]
    with pytest.raises(ValueError, match="unknown model"):
        _model_names(["phong_9"])


@pytest.mark.parametrize(
    ("name", "shown"),
    [
        ("ggx", "capture model"),
        ("cook_torrance_ggx", "ggx (given as cook_torrance_ggx)"),
        ("cook_torrance", "BRDF family"),
        ("lafortune_2", "measured-BRDF model"),
        ("ggx_normal", "tilt_x"),
    ],
)
def test_models_describes_any_name(capsys, name, shown):
    assert main(["models", name]) == 0
    out = capsys.readouterr().out
    assert shown in out and "parameters" in out


def test_models_refuses_an_unknown_name(capsys):
    assert main(["models", "nope"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxrefl models: error: unknown model 'nope'") and "ggx" in err
    assert len(err.splitlines()) == 1


# ------------------------------------------------------------------------------- argument errors
ARG_ERRORS = [
    (["fit", "c", "--out", "o", "--downsample", "0"], "argument --downsample: must be >= 1"),
    (["fit", "c", "--out", "o", "--holdout", "-1"], "argument --holdout"),
    (["fit", "c", "--out", "o", "--alpha-min", "2"], "argument --alpha-min: must be in (0, 1]"),
    (["fit", "c", "--out", "o", "--tilt-std", "0"], "argument --tilt-std: must be > 0"),
    (["fit", "c", "--out", "o", "--model", "ggx9"], "argument --model: invalid choice"),
    (["demo", "--size", "30"], "argument --size: must be a multiple of 4"),
    (["demo", "--noise", "-1"], "argument --noise: must be >= 0"),
    (["demo", "--seed", "x"], "argument --seed"),
    (["ps", "c", "--out", "o", "--downsample", "0"], "argument --downsample: must be >= 1"),
    (["sample", "c", "--out", "o", "--audit", "1.5"], "argument --audit: must be in [0, 1]"),
    (["sample", "c", "--out", "o", "--rerun-rhat", "0.5"], "argument --rerun-rhat"),
    (["sample", "c", "--out", "o", "--warmup", "-1"], "argument --warmup: must be >= 0"),
    (["fit-brdf", "f", "--out", "o", "--sample", "62"], "argument --sample: CURET has samples"),
    (["fit-brdf", "f", "--out", "o", "--max-theta", "95"], "argument --max-theta"),
    (["fit-brdf", "f", "--out", "o", "--max-theta=-inf"], "expected a finite number"),
    (["fit-brdf", "f", "--out", "o", "--thetas", "-5"], "must be in [0, 90) degrees"),
    (["fit-brdf", "f", "--out", "o", "--thetas", "x"], "argument --thetas: expected a number"),
    (["fit-brdf", "f", "--out", "o", "--merl-samples", "-3"], "argument --merl-samples"),
    (["fit-brdf", "f", "--out", "o", "--max-iters", "0"], "argument --max-iters"),
    (["fit", "c"], "the following arguments are required: --out"),
]


@pytest.mark.parametrize(("argv", "message"), ARG_ERRORS)
def test_argument_errors_are_one_line(capsys, argv, message):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"jaxrefl {argv[0]}: error: ") and message in last, err


# ------------------------------------------------------------------------------- OSErrors
def test_out_naming_a_file_is_one_line(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("x")
    for argv in (
        ["fit", str(tmp_path), "--out", str(f), "--no-compile-cache"],
        ["demo", "--out", str(f), "--no-fit", "--no-compile-cache"],
        ["fit-brdf", str(tmp_path / "x.astm"), "--out", str(f), "--no-compile-cache"],
        ["fit", str(tmp_path), "--out", str(f / "sub"), "--no-compile-cache"],
    ):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(f) in err and "not a folder" in err, err


@pytest.mark.parametrize(
    "exc",
    [
        PermissionError(13, "Permission denied", "/data/capture/00.png"),
        IsADirectoryError(21, "Is a directory", "/data/capture/00.png"),
        OSError(28, "No space left on device", "/data/capture/00.png"),
    ],
)
def test_any_oserror_is_one_line_naming_the_path(monkeypatch, capsys, tmp_path, exc):
    import jaxrefl.io

    def fail(*a, **k):
        raise exc

    monkeypatch.setattr(jaxrefl.io, "load_capture", fail)
    assert main(["fit", str(tmp_path), "--out", str(tmp_path / "o"), "--no-compile-cache"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"jaxrefl fit: error: /data/capture/00.png: {exc.strerror}"


# ------------------------------------------------------------------------------- fit plumbing
class _FakeFit:
    """Stands in for the library calls of ``jaxrefl fit`` (their own tests run them): writes
    a tile as fit_capture does, or is interrupted after it."""

    def __init__(self, interrupt: bool = False):
        self.interrupt = interrupt

    def install(self, monkeypatch):
        import jaxrefl.cli._fit as cli_fit
        import jaxrefl.io
        import jaxrefl.svbrdf

        monkeypatch.setattr(jaxrefl.io, "load_capture", lambda *a, **k: "capture")
        monkeypatch.setattr(jaxrefl.svbrdf, "fit_capture", self.fit_capture)
        monkeypatch.setattr(jaxrefl.svbrdf, "write_outputs", self.write_outputs)
        monkeypatch.setattr(cli_fit, "print_summary", lambda report: None)

    def fit_capture(self, capture, job, out, restart=False, progress=True, distributed=None):
        tiles = Path(out) / "tiles"
        tiles.mkdir(parents=True, exist_ok=True)
        (tiles / "tile_00000.npz").write_bytes(b"")
        if self.interrupt:
            raise KeyboardInterrupt

        class Result:
            report: dict = {}  # noqa: RUF012

        return Result()

    def write_outputs(self, result, capture, out, previews=True):
        return {"maps": str(Path(out) / "maps.exr"), "report": str(Path(out) / "report.json")}


@pytest.mark.parametrize("keep", [False, True])
def test_keep_tiles(monkeypatch, tmp_path, capsys, keep):
    _FakeFit().install(monkeypatch)
    out = tmp_path / "o"
    argv = ["fit", str(tmp_path), "--out", str(out), "--quiet", "--no-compile-cache"]
    assert main(argv + (["--keep-tiles"] if keep else [])) == 0
    assert (out / "tiles").exists() == keep


def test_ctrl_c_is_one_line_exit_130_and_says_how_to_resume(monkeypatch, tmp_path, capsys):
    _FakeFit(interrupt=True).install(monkeypatch)
    out = tmp_path / "o"
    assert main(["fit", str(tmp_path), "--out", str(out), "--no-compile-cache"]) == 130
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith("jaxrefl fit: interrupted") and "run the same command to resume" in err
    assert (out / "tiles" / "tile_00000.npz").exists()  # kept for the resume


def test_ctrl_c_without_resume(monkeypatch, capsys):
    import jaxrefl.cli._models as cli_models

    def stop(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_models, "run", stop)
    assert main(["models"]) == 130
    assert capsys.readouterr().err.strip() == "jaxrefl models: interrupted"


def test_backend_needs_its_extra(monkeypatch):
    import importlib.util

    from jaxrefl.cli._options import solver_from_flags

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "optimistix" else real(n, *a)
    )
    with pytest.raises(ValueError, match=r"pip install 'jaxrefl\[backends\]'"):
        solver_from_flags("optimistix")


# ------------------------------------------------------------------------------- compile cache
def test_compile_cache_folder(monkeypatch, tmp_path):
    from jaxrefl.cli._compile import chosen_cache_dir

    monkeypatch.delenv("JAXREFL_NO_COMPILE_CACHE", raising=False)
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert chosen_cache_dir() == tmp_path / "jaxrefl" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert chosen_cache_dir() == tmp_path / "home" / ".cache" / "jaxrefl" / "jax"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "mine"))
    assert chosen_cache_dir() == tmp_path / "mine"  # JAX's own setting wins
    assert chosen_cache_dir(off=True) is None  # --no-compile-cache
    monkeypatch.setenv("JAXREFL_NO_COMPILE_CACHE", "1")
    assert chosen_cache_dir() is None


def test_loop_emitters_unless_the_user_chose(monkeypatch, tmp_path):
    from jaxrefl.cli._compile import LOOP_EMITTERS, prefer_loop_emitters

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    assert prefer_loop_emitters()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_enable_fast_math=false", LOOP_EMITTERS]
    assert prefer_loop_emitters()  # once only
    assert os.environ["XLA_FLAGS"].count("fusion_emitters") == 1
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert not prefer_loop_emitters()  # the user's choice is kept
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    # The command line sets it before its work (here a fit refused for a missing folder).
    monkeypatch.delenv("XLA_FLAGS")
    assert main(["fit", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    assert os.environ["XLA_FLAGS"] == LOOP_EMITTERS


def test_compile_line_counts_programs(capsys):
    import jax
    import jax.numpy as jnp

    from jaxrefl.cli._compile import CompileClock

    clock = CompileClock().start()
    try:
        jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.25)(jnp.arange(7.0)).block_until_ready()
    finally:
        clock.stop()
    assert clock.programs >= 1 and clock.seconds > 0
    assert clock.line(None).startswith("compiling: ")
