"""``jaxrefl plan`` from the folder of a ``pooled`` fit (the model ``auto`` chooses for the
real flash captures): the report records the lower bound of the shared width, and the plan
frees that width from it."""

from __future__ import annotations

import json

from jaxrefl.cli import main


def test_plan_reads_back_a_pooled_fit(tmp_path):
    demo, fit_dir, plan_dir = tmp_path / "demo", tmp_path / "fit", tmp_path / "plan"
    assert main(["demo", "--out", str(demo), "--size", "8", "--no-fit"]) == 0
    fit_args = ["fit", str(demo), "--out", str(fit_dir), "--model", "pooled", "--quiet"]
    assert main([*fit_args, "--photos", "0,3,5,6,8", "--no-previews"]) == 0
    report = json.loads((fit_dir / "report.json").read_text())
    assert report["pooled"]["alpha"] is not None  # the demo's lobe is seen: a shared width
    assert 0 < report["alpha_min"] <= report["pooled"]["alpha"]
    plan_args = ["plan", str(fit_dir), "--out", str(plan_dir), "--candidates-from", str(demo)]
    assert main([*plan_args, "--photos", "1,2,4,7"]) == 0
    ranking = json.loads((plan_dir / "plan.json").read_text())["ranking"]
    assert sorted(r["photo"] for r in ranking) == [1, 2, 4, 7]
    gains = [r["gain"] for r in ranking]
    assert gains == sorted(gains, reverse=True) and gains[0] > 0
