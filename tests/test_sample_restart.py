"""``jaxrefl sample``'s resumable work: a rerun of another job in the same OUT folder is
refused with the way out the message names (``--restart``), which discards the work and
starts over, and another capture's work is refused before any fitting; a whole map leaves
no work folder behind (a pooled map's widths included)."""

from __future__ import annotations

import pytest

from jaxrefl import svbrdf
from jaxrefl._errors import JaxreflError
from jaxrefl.cli import main
from jaxrefl.cli._sample import work_dirs
from jaxrefl.io import load_capture
from jaxrefl.svbrdf import _job


def test_restart_discards_another_jobs_work(tmp_path, capsys):
    cap = tmp_path / "cap"
    assert main(["demo", "--out", str(cap), "--size", "8", "--no-fit"]) == 0
    out = tmp_path / "out"
    base = ["sample", str(cap), "--out", str(out), "--model", "lambert", "--quiet"]
    assert main([*base, "--pixels", "0:3,0:3", "--keep-work"]) == 0
    assert [d.name for d in work_dirs(out)] == ["fit", "mcmc"]
    capsys.readouterr()
    # another crop (of the same size: the same compiled programs) is another job: refused,
    # with the flag that resolves it
    assert main([*base, "--pixels", "1:4,1:4"]) != 0
    err = capsys.readouterr().err
    assert "belongs to a different job" in err and "--restart" in err
    assert main([*base, "--pixels", "1:4,1:4", "--restart"]) == 0
    assert work_dirs(out) == []  # whole map, no --keep-work: nothing left to resume


def test_work_dirs_name_every_resumable_folder(tmp_path):
    for name in ("fit", "mcmc", "fit_widths", "fit_ggx_rgb", "previews"):
        (tmp_path / name).mkdir()
    (tmp_path / "fit_notes").write_text("a file, not work")
    names = [d.name for d in work_dirs(tmp_path)]
    assert names == ["fit", "fit_ggx_rgb", "fit_widths", "mcmc"]
    assert work_dirs(tmp_path / "missing") == []


def test_another_captures_work_is_refused_before_the_light_and_model_choice(tmp_path, monkeypatch):
    """``fit_capture`` refuses an OUT folder whose tiles hold another capture (here another
    crop) before it estimates the light or chooses a model, which take a minute on a large
    capture; ``restart`` goes on."""
    cap = tmp_path / "cap"
    assert main(["demo", "--out", str(cap), "--size", "8", "--no-fit"]) == 0
    full = load_capture(cap)
    out = tmp_path / "out"
    job = svbrdf.FitJob(model="lambert", light="fixed")
    svbrdf.fit_capture(full.crop(0, 3, 0, 3), job, out)
    calls = []

    def light(*a, **k):
        calls.append("light")
        raise AssertionError("the light was estimated before the refusal")

    monkeypatch.setattr(_job, "estimate_light", light)
    other = svbrdf.FitJob(model="auto", light="auto")
    with pytest.raises(JaxreflError, match=r"differs in: capture\); use --restart"):
        svbrdf.fit_capture(full.crop(0, 4, 0, 4), other, out)
    assert calls == []
    with pytest.raises(AssertionError, match="the light was estimated"):
        svbrdf.fit_capture(full.crop(0, 4, 0, 4), other, out, restart=True)
    # the same capture passes the early check (its job is then checked with the tiles)
    monkeypatch.undo()
    svbrdf.fit_capture(full.crop(0, 3, 0, 3), job, out)
