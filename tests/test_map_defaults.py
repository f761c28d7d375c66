"""One uncertainty map, one default: ``AdaptiveOptions()``, ``jaxrefl sample CAPTURE`` and
the docs all read :mod:`jaxrefl._map_defaults`. The same small capture sampled through the
library and through the command line records the same sampler settings in its report."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from jaxrefl import _map_defaults as d
from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.cli import main
from jaxrefl.cli._main import build_parser
from jaxrefl.io import load_capture

ROOT = Path(__file__).resolve().parents[1]


def test_library_and_command_line_make_the_same_map(tmp_path):
    """A 3 x 3 crop of the demo capture, no sampler flag given: the command's report.json
    and the library's report (``AdaptiveOptions()``) record the same first and second pass
    settings, and the same pixels took each method."""
    cap = tmp_path / "cap"
    assert main(["demo", "--out", str(cap), "--size", "8", "--no-fit"]) == 0
    out = tmp_path / "out"
    argv = ["sample", str(cap), "--out", str(out), "--model", "lambert", "--pixels", "0:3,0:3"]
    assert main([*argv, "--quiet"]) == 0
    cli = json.loads((out / "report.json").read_text())
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64))
    lib = svbrdf.uncertainty_maps(load_capture(cap).crop(0, 3, 0, 3), job).report()
    lib = json.loads(json.dumps(lib, default=str))  # the JSON types the command wrote
    assert cli["sampler"] == lib["sampler"]
    assert cli["second_pass"] == lib["second_pass"]
    assert cli["uncertainty"]["method_counts"] == lib["uncertainty"]["method_counts"]
    o = jp.AdaptiveOptions()
    assert cli["sampler"]["num_warmup"] == o.hmc.num_warmup == d.MAP_SAMPLER["num_warmup"]
    assert cli["sampler"]["gibbs"]["sweeps"] == o.gibbs.sweeps == d.MAP_GIBBS["sweeps"]


def test_the_command_line_and_the_options_read_one_defaults_module():
    """The command's flag defaults and ``AdaptiveOptions()`` are the values of
    :mod:`jaxrefl._map_defaults`; the docs point there and at the names that carry them."""
    o = jp.AdaptiveOptions()
    assert o.hmc == jp.UNCERTAINTY_MAP_HMC == jp.HMCOptions(**d.MAP_SAMPLER)
    assert o.gibbs == jp.UNCERTAINTY_MAP_GIBBS == jp.GibbsOptions(**d.MAP_GIBBS)
    assert (o.audit, o.chunk, o.rerun_rhat) == (d.MAP_AUDIT, d.MAP_CHUNK, d.RERUN_RHAT)
    args = build_parser().parse_args(["sample", "c", "--out", "o"])
    assert (args.audit, args.chunk, args.gibbs_sweeps) == (
        d.MAP_AUDIT,
        d.MAP_CHUNK,
        d.MAP_GIBBS["sweeps"],
    )
    arch = (ROOT / "docs" / "architecture.md").read_text()
    assert "jaxrefl._map_defaults" in arch and "UNCERTAINTY_MAP_HMC" in arch
    # The docs name the defaults, never their values (docs/benchmarks.md records runs).
    numbers = [d.RERUN_RHAT, d.MAP_AUDIT, d.MAP_CHUNK, d.MAP_KEEP_PIXELS]
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = doc.read_text()
        assert "MAP_OPTIONS" not in text, doc.name
        if doc.name != "benchmarks.md":
            for v in numbers:
                assert not re.search(rf"(?<![\w.]){re.escape(f'{v:g}')}(?![\w.])", text), (
                    f"{doc.name} restates {v:g} of jaxrefl._map_defaults"
                )


def test_the_rhat_map_marks_the_pixels_the_map_reruns():
    """``rhat.png`` marks the pixels above the map's own threshold: its options' second-pass
    R-hat, or the default one where the map runs no second pass."""
    from jaxrefl.svbrdf._uncertainty_plots import rhat_mark

    assert rhat_mark(jp.AdaptiveOptions()) == d.RERUN_RHAT
    assert rhat_mark(jp.AdaptiveOptions(rerun_rhat=1.2)) == 1.2
    assert rhat_mark(jp.AdaptiveOptions(rerun_rhat=None)) == d.RERUN_RHAT


def test_posterior_all_is_what_the_architecture_documents():
    """``jaxrefl.posterior.__all__`` is the list docs/architecture.md gives, and every name
    the package exports."""
    arch = (ROOT / "docs" / "architecture.md").read_text()
    seg = arch[arch.index("<!-- posterior-all -->") :]
    documented = set(re.findall(r"`(\w+)`", seg[: seg.index("\n\n")]))
    assert set(jp.__all__) == documented
    public = {n for n in vars(jp) if not n.startswith("_")}
    assert set(jp.__all__) <= public
