"""HMC's seed has one home, ``HMCOptions.seed``: it seeds one material's chains
(``measured.sample_posterior``, ``jaxrefl sample FILE --sampler hmc --seed N``), and an
uncertainty map, whose chunks are seeded by ``AdaptiveOptions.seed``, refuses it."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from jaxrefl import measured as jm
from jaxrefl import posterior as jp
from jaxrefl.cli import main

SHORT = {"num_warmup": 20, "num_samples": 20, "num_chains": 2}


def test_hmc_seed_on_a_brdf_file(shared_data, tmp_path):
    """--seed seeds HMC's chains on a BRDF file: the library with the same seed gives the
    command's draws, another seed other draws; the report records the seed that ran."""
    az = pytest.importorskip("arviz")
    src = shared_data / "brdf" / "cornell" / "acryl_blue.astm"
    out = tmp_path / "hmc"
    argv = ["sample", str(src), "--out", str(out), "--brdf-model", "lambert", "--quiet"]
    argv += ["--sampler", "hmc", "--seed", "2", "--warmup", "20", "--samples", "20"]
    argv += ["--chains", "2"]
    assert main(argv) in (0, 3)  # 3: written, but 20 draws miss the convergence targets
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["sampler"]["seed"] == 2
    post = az.from_netcdf(str(out / "posterior.nc"))
    two = jm.sample_posterior(src, "lambert", jp.HMCOptions(**SHORT, seed=2))
    assert two.samples.method == "hmc"
    lab = two.samples.labels[0]
    drawn = post.posterior[lab.replace(".", "_")].values  # (chains, draws)
    np.testing.assert_array_equal(two.samples.natural[0, ..., 0], drawn)
    assert two.report()["settings"]["sampler"]["seed"] == 2
    # None: the caller's seed, measured.HMC_SEED for one material
    unset = jm.sample_posterior(src, "lambert", jp.HMCOptions(**SHORT))
    other = jm.sample_posterior(src, "lambert", jp.HMCOptions(**SHORT, seed=jm.HMC_SEED))
    np.testing.assert_array_equal(unset.samples.theta, other.samples.theta)
    # another seed (measured.HMC_SEED is not 2), other draws
    assert jm.HMC_SEED != 2 and not np.allclose(two.samples.theta, other.samples.theta)
    assert unset.report()["settings"]["sampler"]["seed"] == jm.HMC_SEED


def test_a_map_refuses_hmc_seed():
    """A map's chains are seeded by AdaptiveOptions.seed: an HMCOptions seed is refused,
    in either pass, with a message that says where the seed goes."""
    with pytest.raises(ValueError, match=r"seeded by AdaptiveOptions\.seed"):
        jp.AdaptiveOptions(hmc=jp.HMCOptions(seed=1))
    with pytest.raises(ValueError, match=r"rerun_hmc has seed=4"):
        jp.AdaptiveOptions(rerun_hmc=replace(jp.UNCERTAINTY_MAP_HMC, seed=4))
    jp.AdaptiveOptions(hmc=jp.HMCOptions(seed=None), seed=5)  # the map's own seed: fine
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        jp.HMCOptions(seed=-1)
    # one call, one seed: sample_pixels' argument and the options' may not disagree
    with pytest.raises(ValueError, match=r"seed=2 and HMCOptions\.seed=1: give one"):
        jp.sample_pixels(None, None, np.zeros(3), options=jp.HMCOptions(seed=1), seed=2)
