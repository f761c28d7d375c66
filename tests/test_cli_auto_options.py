"""The model choice's settings from the command line: ``--auto-candidates``,
``--auto-pixels`` and ``--auto-seed`` of ``jaxrefl fit`` and ``jaxrefl sample CAPTURE``
become the job's :class:`~jaxrefl.svbrdf.AutoOptions` (flags not given: its defaults),
an unknown candidate is one line naming the valid models, and a fit's report.json records
what was given."""

from __future__ import annotations

import json

import pytest

from jaxrefl import svbrdf
from jaxrefl._names import CAPTURE_MODELS
from jaxrefl.cli import _fit as fit_cmd
from jaxrefl.cli import _sample as sample_cmd
from jaxrefl.cli import main
from jaxrefl.cli._main import build_parser

FLAGS = ["--auto-candidates", "Lambert,ggx-rgb", "--auto-pixels", "512", "--auto-seed", "3"]
GIVEN = svbrdf.AutoOptions(candidates=("lambert", "ggx_rgb"), max_pixels=512, seed=3)


def _parse(*argv: str):
    return build_parser().parse_args(list(argv))


@pytest.mark.parametrize("job_of", [fit_cmd.fit_job, sample_cmd._job], ids=["fit", "sample"])
def test_the_flags_reach_the_jobs_auto(job_of):
    """Given, the flags are the job's ``auto`` (names canonical); one flag alone changes
    that setting only; none given, the job's ``auto`` is ``AutoOptions()``."""
    command = "fit" if job_of is fit_cmd.fit_job else "sample"
    base = [command, "capture", "--out", "out"]
    assert job_of(_parse(*base, *FLAGS)).auto == GIVEN
    seed_only = job_of(_parse(*base, "--auto-seed", "11")).auto
    assert seed_only == svbrdf.AutoOptions(seed=11)
    default = svbrdf.AutoOptions()
    assert job_of(_parse(*base)).auto == default
    assert default.candidates == svbrdf.AUTO_CANDIDATES  # the name --help gives as default


@pytest.mark.parametrize("command", ["fit", "sample"])
def test_an_unknown_candidate_is_one_line_naming_the_models(tmp_path, capsys, command):
    """Checked before any file is read (the folder holds no capture): exit status 1, one
    line that names the flag, the bad name and every capture model."""
    argv = [command, str(tmp_path), "--out", str(tmp_path / "o"), "--no-compile-cache"]
    assert main([*argv, "--auto-candidates", "lambert,phong"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "--auto-candidates: unknown model 'phong'; choose from" in err
    assert all(m in err for m in CAPTURE_MODELS)


@pytest.mark.parametrize("value", ["lambert,,ggx", "ggx,GGX"])
def test_empty_or_repeated_candidates_are_argument_errors(capsys, value):
    assert main(["fit", "c", "--out", "o", "--auto-candidates", value]) == 2
    err = capsys.readouterr().err
    assert "argument --auto-candidates: takes distinct capture model names separated" in err


def test_a_fit_records_the_given_choice_settings(tmp_path):
    """``jaxrefl fit`` on the 8 x 8 demo capture (Lambert the one candidate, the light as
    stated: the choice scores one cheap model): report.json's ``auto`` and ``job.auto``
    hold the flags' candidates, pixel count and seed."""
    cap, out = tmp_path / "cap", tmp_path / "fit"
    assert main(["demo", "--out", str(cap), "--size", "8", "--no-fit"]) == 0
    argv = ["fit", str(cap), "--out", str(out), "--quiet", "--no-previews", "--light", "fixed"]
    flags = ["--auto-candidates", "lambert", "--auto-pixels", "300", "--auto-seed", "7"]
    assert main([*argv, *flags]) == 0
    report = json.loads((out / "report.json").read_text())
    given = {"candidates": ["lambert"], "max_pixels": 300, "seed": 7}
    assert {k: report["auto"][k] for k in given} == given
    assert report["job"]["auto"] == given
    assert report["auto"]["model"] == report["model"] == "lambert"
