"""Reports are strict JSON (``jaxrefl._jsonsafe``): non-finite numbers become null with a
record of what they were, numpy values become plain JSON, and the CLI writes reports so.

Every report.json that a test leaves under its ``tmp_path`` is also parsed strictly after
the test (``tests/conftest.py``); here are the writer's own cases and a CLI report with an
undefined metric.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl._jsonsafe import NULLS_KEY, jsonable, report_json
from jaxrefl.cli import main


def test_non_finite_numbers_nested_in_dicts_and_lists_become_null_with_their_place():
    obj = {
        "a": float("nan"),
        "b": [1.0, float("inf"), (2, -math.inf)],
        "c": {"d": {"e": np.float32("nan")}, "ok": np.float64(0.5)},
        "arr": np.array([[1.0, np.nan], [np.inf, 2.0]]),
    }
    clean, nulls = jsonable(obj)
    assert clean == {
        "a": None,
        "b": [1.0, None, [2, None]],
        "c": {"d": {"e": None}, "ok": 0.5},
        "arr": [[1.0, None], [None, 2.0]],
    }
    assert nulls == {
        "/a": "NaN",
        "/b/1": "Infinity",
        "/b/2/1": "-Infinity",
        "/c/d/e": "NaN",
        "/arr/0/1": "NaN",
        "/arr/1/0": "Infinity",
    }


def test_numpy_and_jax_values_become_plain_python():
    clean, nulls = jsonable(
        {
            "i": np.int64(3),
            "b": np.bool_(True),
            "f": np.float32(0.25),
            "a": np.arange(3, dtype=np.int32),
            "j": jnp.asarray([0.5, jnp.nan]),
            "p": Path("out") / "maps.exr",
            "t": (1, "x"),
            7: "int key",
        }
    )
    assert clean == {
        "i": 3,
        "b": True,
        "f": 0.25,
        "a": [0, 1, 2],
        "j": [0.5, None],
        "p": str(Path("out") / "maps.exr"),
        "t": [1, "x"],
        "7": "int key",
    }
    assert type(clean["i"]) is int and type(clean["b"]) is bool and type(clean["f"]) is float
    assert nulls == {"/j/1": "NaN"}


def test_pointers_escape_slash_and_tilde_and_keep_dotted_labels():
    _, nulls = jsonable({"a/b": {"~c": math.nan}, "albedo.R": [math.inf], "": -math.inf})
    assert nulls == {"/a~1b/~0c": "NaN", "/albedo.R/0": "Infinity", "/": "-Infinity"}
    assert jsonable(math.nan) == (None, {"": "NaN"})


def test_report_json_is_strict_and_records_its_nulls(strict_json):
    text = report_json({"timings": {"compile_s": math.nan, "run_s": 1.5}, "rmse": [np.inf]})
    assert text.endswith("\n")
    rep = strict_json(text)
    assert rep["timings"] == {"compile_s": None, "run_s": 1.5} and rep["rmse"] == [None]
    assert rep[NULLS_KEY] == {"/timings/compile_s": "NaN", "/rmse/0": "Infinity"}
    # All finite: no record.
    assert NULLS_KEY not in strict_json(report_json({"x": 1.0, "y": [np.float64(2.0)]}))


def test_report_json_refuses_what_it_cannot_write_faithfully():
    with pytest.raises(ValueError, match="nulls"):
        report_json({NULLS_KEY: {}})
    with pytest.raises(TypeError, match="/a/0"):
        report_json({"a": [object()]})
    with pytest.raises(TypeError, match="complex"):
        report_json({"z": 1j})
    # ``default`` converts other objects, and its result is made safe in turn.
    rep = json.loads(report_json({"a": [object()]}, default=lambda o: math.nan))
    assert rep == {"a": [None], NULLS_KEY: {"/a/0": "NaN"}}


def test_strict_parser_refuses_nan_tokens(strict_json):
    # The check the suite applies to every report.json (conftest) does reject Python's NaN.
    with pytest.raises(ValueError, match="NaN"):
        strict_json(json.dumps({"x": math.nan}))
    with pytest.raises(ValueError, match="Infinity"):
        strict_json(json.dumps([-math.inf]))


def test_sample_report_writer_is_strict(tmp_path, strict_json):
    # ``sample --sampler hmc`` on a BRDF file reports compile_s = NaN (not measured apart).
    from jaxrefl.cli._sample import _json

    _json(tmp_path / "report.json", {"timings": {"compile_s": np.float64(np.nan)}})
    rep = strict_json((tmp_path / "report.json").read_text())
    assert rep["timings"]["compile_s"] is None
    assert rep[NULLS_KEY] == {"/timings/compile_s": "NaN"}


def test_fit_brdf_report_of_an_all_zero_file_is_strict(shared_data, tmp_path, strict_json):
    """relative_l2 = |fhat - f| / |f| is 0/0 for a file of zeros: null, recorded as NaN."""
    lines = (shared_data / "brdf/cornell/acryl_blue.astm").read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("VARS")) + 1
    rows = [line.split(",") for line in lines[head:] if line.strip()][:40]
    header = [f"NUM_POINTS {len(rows)}" if h.startswith("NUM_POINTS") else h for h in lines[:head]]
    body = [",".join(r[:4] + ["0"] * (len(r) - 4)) for r in rows]
    src = tmp_path / "zero.astm"
    src.write_text("\n".join([*header, "", *body]) + "\n")
    out = tmp_path / "fit"
    assert main(["fit-brdf", str(src), "--models", "lambert", "--no-plot", "--out", str(out)]) == 0
    rep = strict_json((out / "report.json").read_text())
    assert rep["models"]["lambert"]["metrics"]["relative_l2"] is None
    assert rep[NULLS_KEY]["/models/lambert/metrics/relative_l2"] == "NaN"
