"""The corner plot of a pixel's draws (jaxrefl.posterior.plot_corner): the lower triangle
of pairwise scatters over the marginal histograms, each column sharing its parameter's axis,
tick labels on the outer axes only."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from jaxrefl.posterior import plot_corner


class _Draws:
    labels = ("albedo.R", "specular.R", "alpha")

    def flat(self, pixel):
        rng = np.random.default_rng(pixel)
        x = rng.normal(size=(400, 3)) * [0.01, 0.002, 0.05] + [0.3, 0.04, 0.2]
        x[:5] = np.nan  # a draw without an estimate is left out, not plotted as NaN
        return x


def test_lower_triangle_with_shared_columns_and_outer_labels(tmp_path):
    fig = plot_corner(_Draws(), 0, truth=np.array([0.3, 0.04, 0.2]))
    axes = fig.axes
    assert len(axes) == 6  # d (d + 1) / 2: the upper triangle is removed
    grid = {
        (ax.get_subplotspec().rowspan.start, ax.get_subplotspec().colspan.start): ax for ax in axes
    }
    assert set(grid) == {(i, j) for i in range(3) for j in range(i + 1)}
    for (i, j), ax in grid.items():
        # a column shows parameter j on x: the scatters' x range is the histogram's
        assert ax.get_xlim() == grid[(j, j)].get_xlim()
        if i > j > 0:
            assert ax.get_ylim() == grid[(i, 0)].get_ylim()
    fig.canvas.draw()  # tick labels get their text when drawn
    for (i, j), ax in grid.items():
        shows_x = any(t.get_visible() and t.get_text() for t in ax.get_xticklabels())
        shows_y = any(t.get_visible() and t.get_text() for t in ax.get_yticklabels())
        assert shows_x == (i == 2), (i, j)
        assert shows_y == (j == 0 and i > 0), (i, j)
    assert grid[(2, 0)].get_xlabel() == "albedo.R" and grid[(2, 0)].get_ylabel() == "alpha"
    # every finite draw is plotted, the NaN ones are not
    points = grid[(1, 0)].lines[0].get_xdata()
    assert points.size == 395 and np.all(np.isfinite(points))
    fig.savefig(tmp_path / "corner.png", dpi=50)
    assert (tmp_path / "corner.png").stat().st_size > 0
    plt.close(fig)
