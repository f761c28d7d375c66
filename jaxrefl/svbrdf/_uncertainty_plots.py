"""PNG figures of a capture's uncertainty maps: what a user looks at first.

:func:`write_uncertainty_plots` writes, for a :class:`CaptureUncertainty`,

- ``posterior_std.png``: the posterior std of every parameter (Laplace or MCMC, whichever
  the pixel used), one panel each, on a log colour scale from the 1st to the 99th
  percentile, with a colour bar in the parameter's units (:data:`STD_UNITS`);
- ``rhat.png`` (where pixels were sampled): the max split R-hat of every MCMC pixel (grey:
  no MCMC), with the pixels above the map's convergence threshold (:func:`rhat_mark`)
  marked by red crosses and counted in the title;
- ``pair_rROW_cCOL.png`` (where draws were kept): pairwise scatter and marginal histograms
  of the draws (:func:`jaxrefl.posterior.plot_corner`) for up to ``n_pairs`` MCMC pixels:
  the one of largest R-hat first, then pixels spread evenly over the rest.

Maps larger than ``side`` pixels a side are shown strided. Matplotlib runs headless (Agg).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from jaxrefl import posterior as jp
from jaxrefl._map_defaults import RERUN_RHAT

from ._outputs import _log_std

if TYPE_CHECKING:
    from ._uncertainty import CaptureUncertainty

__all__ = ["STD_UNITS", "rhat_mark", "write_uncertainty_plots"]

# Units of each parameter block's std (the natural units of the capture models).
STD_UNITS = {
    "albedo": "diffuse albedo, 1",
    "specular": "Schlick F0, 1",
    "alpha": "GGX alpha, 1",
    "roughness": "perceptual roughness, 1",
    "normal": "normal component, 1",
    "noise_scale": "multiple of the noise model's std, 1",
}


def rhat_mark(options: jp.AdaptiveOptions) -> float:
    """The max split R-hat above which a map's pixel is marked as not mixed: the threshold
    above which the map reran it (``options.rerun_rhat``), or the map's default
    (:data:`jaxrefl._map_defaults.RERUN_RHAT`) where the map runs no second pass."""
    return RERUN_RHAT if options.rerun_rhat is None else float(options.rerun_rhat)


def _units(label: str) -> str:
    return STD_UNITS.get(label.split(".")[0], "natural units")


def write_uncertainty_plots(
    result: CaptureUncertainty, out_dir: str | Path, *, n_pairs: int = 3, side: int = 384
) -> list[Path]:
    """Write the PNGs of the module docstring into ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    h, w, u = result.height, result.width, result.map
    step = max(1, -(-max(h, w) // side))
    paths: list[Path] = []

    def save(fig, name: str, layout: bool = True) -> None:
        # layout=False: the figure placed its axes itself (plot_corner's fixed margins)
        if layout:
            fig.tight_layout()
        paths.append(out / name)
        fig.savefig(paths[-1], dpi=90, bbox_inches="tight" if layout else None)
        plt.close(fig)

    labels = u.labels
    cols = min(4, len(labels))
    rows = -(-len(labels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat[len(labels) :]:
        ax.axis("off")
    for j, lab in enumerate(labels):
        v = np.asarray(u.std[:, j], np.float64).reshape(h, w)[::step, ::step]
        _log_std(fig, axes.flat[j], v, f"posterior std of {lab}", _units(lab))
    save(fig, "posterior_std.png")

    on = np.isfinite(u.rhat)
    if np.any(on):
        rhat = np.asarray(u.rhat, np.float64).reshape(h, w)
        fig, ax = plt.subplots(1, 1, figsize=(4.6, 4.2))
        cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.6")  # grey: no MCMC
        # The colour scale reaches 1.1 at least, so chains that all mixed are not coloured
        # as if their small spread of R-hat were a spread of failures.
        hi = max(1.1, float(np.nanmax(rhat)))
        im = ax.imshow(rhat[::step, ::step], cmap=cmap, vmin=1.0, vmax=hi)
        mark = rhat_mark(result.options)
        r, c = np.nonzero(rhat[::step, ::step] > mark)
        n_bad = int(np.sum(rhat > mark))
        ax.plot(c, r, "x", color="red", ms=5, mew=1.2, label=f"R-hat > {mark:g}")
        ax.set_title(
            f"max split R-hat of MCMC pixels (grey: none)\n{n_bad} of {int(np.sum(on))} "
            f"above {mark:g} (red crosses)",
            fontsize=9,
        )
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046).set_label("R-hat, 1", fontsize=7)
        save(fig, "rhat.png")

    if u.samples is not None and n_pairs > 0:
        idx = u.sample_pixels
        rh = np.nan_to_num(u.rhat[idx], nan=np.inf)
        worst = int(np.argmax(rh))
        rest = [i for i in range(idx.size) if i != worst]
        k = min(len(rest), n_pairs - 1)
        spread = [rest[int(t)] for t in np.linspace(0, len(rest) - 1, k).round()] if k else []
        for i in list(dict.fromkeys([worst, *spread])):
            row, col = divmod(int(idx[i]), w)
            fig = jp.plot_corner(u.samples, i)
            fig.suptitle(f"pixel row {row}, col {col}: max R-hat {u.rhat[idx[i]]:.3f}", fontsize=9)
            save(fig, f"pair_r{row}_c{col}.png", layout=False)
    return paths
