"""``jaxrefl sample BRDF_FILE`` samples with the library's own defaults: the sampler flags
left out, its emcee and HMC settings are :class:`~jaxrefl.posterior.EmceeOptions`' and
:class:`~jaxrefl.posterior.HMCOptions`' (the command restates none of their values)."""

from __future__ import annotations

from dataclasses import replace

from jaxrefl import posterior as jp
from jaxrefl.cli._main import build_parser
from jaxrefl.cli._sample import _emcee, _options


def _args(*flags: str):
    return build_parser().parse_args(["sample", "m.astm", "--out", "o", *flags])


def test_a_brdf_files_samplers_are_the_librarys_defaults():
    args = _args()
    assert _emcee(args) == replace(jp.EmceeOptions(), seed=args.seed)
    assert _options(args, brdf_file=True) == jp.HMCOptions()


def test_the_flags_given_replace_those_defaults():
    args = _args("--max-steps", "500", "--walkers", "12", "--seed", "3", "--chains", "2")
    assert _emcee(args) == replace(jp.EmceeOptions(), max_steps=500, n_walkers=12, seed=3)
    assert _options(args, brdf_file=True) == replace(jp.HMCOptions(), num_chains=2)
