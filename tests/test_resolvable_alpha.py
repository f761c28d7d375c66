"""The lower bound of alpha a fit uses (the resolvable width of its photos): only the photos
the fit is given count, not the held-out ones (weight 0)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrefl import svbrdf
from jaxrefl.io import load_capture
from jaxrefl.svbrdf._tile_fitter import TileFitter

BATH = "svbrdf_flash/bath_tile"


def test_resolvable_alpha_counts_the_photos_in_use(shared_data):
    bath = load_capture(shared_data / BATH, resolution=16, max_photos=9)
    use = np.zeros(bath.n_photos, bool)
    use[:5] = True
    alone = svbrdf.resolvable_alpha(bath.select(use))
    assert svbrdf.resolvable_alpha(bath, photos=use) == alone
    # the photos left out sit between those in use: counted, they would narrow the bound
    assert svbrdf.resolvable_alpha(bath) < alone


def test_fit_bound_from_training_photos_only(shared_data):
    bath = load_capture(shared_data / BATH, resolution=16, max_photos=9)
    held = (5, 6, 7, 8)
    train = [i for i in range(bath.n_photos) if i not in held]
    fitter = TileFitter(bath, svbrdf.FitJob(model="ggx", holdout=held))
    assert fitter.alpha_min == pytest.approx(svbrdf.resolvable_alpha(bath.select(train)))
    assert fitter.alpha_min > svbrdf.resolvable_alpha(bath)
    # a bound the job states is kept whatever the photos
    stated = TileFitter(bath, svbrdf.FitJob(model="ggx", holdout=held, alpha_min=0.01))
    assert stated.alpha_min == 0.01


def test_light_problem_widths_from_training_photos_only(shared_data):
    """The light's lobe widths start at the training photos' resolvable width, as the fit's
    bound does: held-out photos do not narrow the grid."""
    from jaxrefl.svbrdf._light_problem import light_problem

    bath = load_capture(shared_data / BATH, resolution=16, max_photos=9)
    train = np.ones(bath.n_photos, bool)
    train[5:] = False
    problem = light_problem(bath, train, n_pixels=16)
    lowest = float(np.exp(np.min(np.asarray(problem.halves[0].grid))))
    assert lowest == pytest.approx(svbrdf.resolvable_alpha(bath.select(train)))
    every = light_problem(bath, np.ones(bath.n_photos, bool), n_pixels=16)
    assert float(np.exp(np.min(np.asarray(every.halves[0].grid)))) < lowest
