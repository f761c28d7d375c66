"""The posterior of an analytic model's parameters given one measured material.

:func:`sample_posterior` fits the model by least squares (:func:`fit_model`, float64, on
the residuals (f̂ - f) cos(theta_i) of the samples within the angle limit, from the
data-driven and quasi-random starts of :class:`MultiStart` solved together: the posterior
starts from the best of them, and the report carries their certificate), then samples
p(theta, s | f) for the same residuals with Gaussian noise of unknown scale s (Jeffreys
prior) and the default priors (:func:`jaxrefl.posterior.default_priors`): the material is
one "pixel" of K samples in C channels (:func:`measured_pixel_data`). The sampler is
chosen by the type of its settings: :class:`jaxrefl.posterior.EmceeOptions` runs emcee
(the default; walkers start about the LM optimum and run until the chain is 50
autocorrelation times long with R-hat <= 1.01 and bulk ESS >= 400, or its ``max_steps``:
:attr:`BRDFPosterior.convergence` says which), :class:`jaxrefl.posterior.HMCOptions`
the batched HMC sampler on this one pixel. Both start from the optimum with the noise
scale at the residual std sqrt(2 cost / (n - P)).

:func:`write_posterior` writes ``posterior.nc`` (ArviZ InferenceData with the observed
data, weights, censoring flags and pointwise log-likelihood) and ``corner.png``;
:meth:`BRDFPosterior.report` is the JSON-ready summary.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl import posterior as jp
from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData
from jaxrefl.io import MeasuredBRDF

from ._data import fit_channels, load_measured, restrict
from ._fit import ModelFit, fit_model
from ._fit_options import MeasuredOptions
from ._models import build_model
from ._prune import measured_pixel_data
from ._start_options import MultiStart

__all__ = ["BRDFPosterior", "sample_posterior", "write_posterior"]

NOISE = "Gaussian on f_r cos(theta_i), unknown scale (Jeffreys prior)"
_MULTISTART = MultiStart()
_OPTIONS = MeasuredOptions()
FILE_DRAWS = 2000  # draws in posterior.nc: with the log-likelihood, ~35 MB for 4,300 values
HMC_SEED = 0  # the HMC chains' seed where HMCOptions.seed is None


@dataclass
class BRDFPosterior:
    """Result of :func:`sample_posterior`.

    model:     the model's name (:func:`build_model`)
    fit:       the least-squares fit (:class:`ModelFit`, float64)
    samples:   the posterior draws (:class:`jaxrefl.posterior.Samples`, one pixel)
    posterior: the log-posterior sampled (:class:`jaxrefl.posterior.LogPosterior`)
    data:      the material's samples as one pixel (K, C), f_r cos(theta_i)
    n_used:    observations (sample x channel) with weight > 0
    sampler:   the sampler's settings; its type says which sampler ran
    timings:   ``fit_s``, seconds in :func:`fit_model`
    settings:  what ran, JSON-ready: the sampler's settings (its seed included), the
               :class:`MeasuredOptions` and the :class:`MultiStart` of the fit
    """

    model: str
    fit: ModelFit
    samples: jp.Samples
    posterior: jp.LogPosterior
    data: PixelData
    n_used: int
    sampler: jp.EmceeOptions | jp.HMCOptions
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def convergence(self) -> jp.Convergence:
        """Whether the draws may be trusted (:func:`jaxrefl.posterior.convergence`): emcee's
        verdict at its stop (chain >= n_tau tau, R-hat, bulk ESS); for HMC, R-hat <=
        1.01 and bulk ESS >= 400 for every parameter."""
        if self.samples.emcee is not None:
            return self.samples.emcee.convergence
        x = self.samples.natural[0]  # (chains, draws, D)
        return jp.convergence(x, labels=self.samples.labels)

    @property
    def sampler_name(self) -> str:
        """``"emcee"`` or ``"hmc"``."""
        return "emcee" if isinstance(self.sampler, jp.EmceeOptions) else "hmc"

    def diagnostics(self) -> dict[str, Any]:
        """:func:`jaxrefl.posterior.diagnostics` of the draws."""
        return jp.diagnostics(self.samples)

    def summary(self) -> dict[str, dict[str, float]]:
        """Per parameter (natural units): mean, std, 5% / 95% quantiles of the draws, split
        R-hat, bulk and tail ESS."""
        dg = self.diagnostics()
        x = self.samples.flat(0)
        return {
            lab: {
                "mean": float(np.mean(x[:, j])),
                "std": float(np.std(x[:, j], ddof=1)),
                "q05": float(np.quantile(x[:, j], 0.05)),
                "q95": float(np.quantile(x[:, j], 0.95)),
                "rhat": float(dg["rhat"][0, j]),
                "ess_bulk": float(dg["ess_bulk"][0, j]),
                "ess_tail": float(dg["ess_tail"][0, j]),
            }
            for j, lab in enumerate(self.samples.labels)
        }

    def inference_data(self, max_draws: int = FILE_DRAWS):
        """ArviZ InferenceData of the draws (no pixel axis: one material) with the observed
        data (dims ``sample``, ``channel`` R/G/B: the samples within the angle limit, in the
        file's order), the likelihood's weights and censoring flags (``constant_data``) and
        the pointwise log-likelihood (``log_likelihood``, float32: ``az.loo`` /
        ``az.compare`` rank models sampled on the same file). Every chain's draws are
        thinned by the smallest step that keeps at most ``max_draws`` in all (attr
        ``file_thin``): the log-likelihood holds draws x observations values."""
        s = self.samples
        _n, c, m, _d = s.theta.shape
        step = max(1, -(-c * m // max_draws))
        s = replace(
            s,
            theta=s.theta[:, :, ::step],
            natural=s.natural[:, :, ::step],
            stats={k: np.asarray(v)[:, :, ::step] for k, v in s.stats.items()},
        )
        one = jax.tree.map(lambda a: a[None], self.data)
        ll = jp.log_likelihood_draws(self.posterior, s, one).astype(np.float32)
        idata = jp.to_inference_data(
            s, one, log_likelihood=ll, observation="sample", attrs={"file_thin": step}
        )
        return idata.isel(pixel=0).map(lambda ds: ds.drop_vars("pixel", errors="ignore"))

    def report(self) -> dict[str, Any]:
        """JSON-ready summary: model, ``converged`` and the :attr:`convergence` verdict (its
        reasons, tau, chain length, R-hat, ESS), sampler, the fit, noise model, :meth:`summary`,
        diagnostics (worst R-hat and ESS, divergences, acceptance; emcee's tau, burn-in and
        thinning), timings and the :attr:`settings` that ran."""
        s, dg, mf = self.samples, self.diagnostics(), self.fit
        run = s.emcee
        emcee: dict[str, Any] = {}
        if run is not None:  # emcee's tau, burn-in and thinning
            emcee = {
                "tau": list(run.tau),
                "burn": run.burn,
                "thin": run.thin,
                "tau_reliable": run.tau_reliable,
                "n_steps": run.n_steps,
                "max_steps": run.max_steps,
                "n_walkers": run.n_walkers,
            }
        return {
            "model": self.model,
            "converged": self.convergence.converged,
            "convergence": self.convergence.to_dict(),
            "sampler": self.sampler_name,
            "samples_used": self.n_used,
            "fit": {
                "params": mf.to_dict()["params"],
                "cost": mf.cost,
                "status": mf.status,
                "certificate": None if mf.certificate is None else mf.certificate.to_dict(),
            },
            "noise": NOISE,
            "posterior": self.summary(),
            "diagnostics": {
                "max_rhat": float(np.max(dg["rhat"])),
                "min_ess_bulk": float(np.min(dg["ess_bulk"])),
                "min_ess_tail": float(np.min(dg["ess_tail"])),
                "divergences": int(dg["divergences"][0]),
                "acceptance": float(dg["acceptance"][0]),
                **emcee,
            },
            "timings": {**self.timings, "compile_s": s.compile_s, "sample_s": s.run_s},
            "settings": self.settings,
        }


def sample_posterior(
    measured: MeasuredBRDF | str | Path,
    model: str,
    sampler: jp.EmceeOptions | jp.HMCOptions | None = None,
    *,
    options: MeasuredOptions = _OPTIONS,
    progress: bool = False,
    starts: MultiStart | None = _MULTISTART,
) -> BRDFPosterior:
    """The posterior of ``model`` (a :func:`build_model` name) given ``measured`` (module
    docstring); spectral data are converted to RGB (:func:`to_rgb`, under
    ``options.illuminant``) first.

    measured:      a :class:`jaxrefl.io.MeasuredBRDF`, or a file :func:`load_measured` reads
    sampler:       :class:`jaxrefl.posterior.EmceeOptions` (None: its defaults; its
                   ``seed`` seeds the walkers) or :class:`jaxrefl.posterior.HMCOptions` (its
                   ``seed`` seeds the chains; None: :data:`HMC_SEED`)
    options:       the samples used and the residual (:class:`MeasuredOptions`: the angle
                   limit, the cosine factor, the illuminant of spectral data; the fit runs in
                   float64, so no retry; ``spectral="bands"`` is refused: one posterior is
                   of one jointly fitted problem)
    progress:      a progress bar over emcee's steps
    starts:        the least-squares fit's starts (:class:`MultiStart`; None: one start)
    """
    m = measured if isinstance(measured, MeasuredBRDF) else load_measured(measured)
    m, channels = fit_channels(m, options)
    if channels != "joint":
        raise JaxreflError(
            "sample_posterior samples one problem, the channels fitted jointly: use "
            "MeasuredOptions(spectral='rgb') for spectral data, or select one band"
        )
    m = restrict(m, options.max_theta_deg)
    sampler = jp.EmceeOptions() if sampler is None else sampler
    brdf = build_model(model)
    t0 = time.perf_counter()
    mf = fit_model(
        brdf,
        m,
        name=model,
        options=options,
        config=fit.FitConfig(dtype=np.float64),
        timing=False,
        starts=starts,
    )
    t_fit = time.perf_counter() - t0
    space = mf.result.space
    data = jax.tree.map(lambda a: a[0], measured_pixel_data(m, cosine=options.cosine))
    lp = jp.log_posterior(brdf, space, fit.GaussianNoise(None))
    theta = np.asarray(mf.result.theta, np.float64)
    n_used = float(np.sum(np.asarray(data.weight) > 0))
    s0 = float(np.sqrt(2 * mf.cost / max(n_used - space.size, 1.0)))
    th0 = lp.init_theta(jnp.asarray(theta), noise_scale=s0)
    if isinstance(sampler, jp.EmceeOptions):
        s = jp.sample_emcee(
            lp,
            th0,
            (data,),
            sampler,
            natural=lp.natural,
            labels=lp.labels,
            progress=progress,
        )
    elif isinstance(sampler, jp.HMCOptions):
        batch = jax.tree.map(lambda a: a[None], data)
        s = jp.sample_pixels(lp, batch, th0[None], options=sampler, seed=_hmc_seed(sampler))
    else:
        raise TypeError(f"sampler must be EmceeOptions or HMCOptions, not {type(sampler).__name__}")
    return BRDFPosterior(
        model=model,
        fit=mf,
        samples=s,
        posterior=lp,
        data=data,
        n_used=int(n_used),
        sampler=sampler,
        timings={"fit_s": t_fit},
        settings={
            "sampler": {"type": s.method, **_sampler_json(sampler)},
            "options": options.to_json(),
            "starts": None if starts is None else starts.to_json(),
        },
    )


def _hmc_seed(sampler: jp.HMCOptions) -> int:
    """The HMC chains' seed: the options', or :data:`HMC_SEED` where they leave it None."""
    return HMC_SEED if sampler.seed is None else sampler.seed


def _sampler_json(sampler: jp.EmceeOptions | jp.HMCOptions) -> dict[str, Any]:
    """The sampler's fields, HMC's seed as it ran (:func:`_hmc_seed`)."""
    out = asdict(sampler)
    return out if isinstance(sampler, jp.EmceeOptions) else {**out, "seed": _hmc_seed(sampler)}


def write_posterior(result: BRDFPosterior, out_dir: str | Path) -> list[Path]:
    """Write ``posterior.nc`` and ``corner.png`` (:func:`jaxrefl.posterior.plot_corner`)
    into ``out_dir`` (created if missing); returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    nc = Path(jp.save_netcdf(result.inference_data(), out / "posterior.nc"))
    fig = jp.plot_corner(result.samples, 0)
    png = out / "corner.png"
    fig.savefig(png, dpi=80)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return [nc, png]
