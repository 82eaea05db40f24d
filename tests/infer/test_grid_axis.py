"""The grid rule of the nested Laplace: log density linear between points, integrated exactly."""

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.special import logsumexp

from bayespd.infer.grid_axis import GridAxis

B, CUSP = 0.05, 0.3  # a Laplace density's scale and centre: a cusp as the horizon's kinks make
GRID = np.concatenate([np.linspace(-0.2, CUSP, 6), np.linspace(CUSP, 0.9, 9)[1:]])  # uneven, the cusp a point


def cusp(x):
    return -np.abs(x - CUSP) / B


def test_exact_for_a_density_exponential_between_points():
    """exp(-|x - c| / b) on an uneven grid with c a point: the rule's integral equals the closed
    form to rounding, where the midpoint rule on the same points errs by percents."""
    axis = GridAxis("d", GRID)
    L = cusp(GRID)
    exact = B * (2 - math.exp(-(CUSP - GRID[0]) / B) - math.exp(-(GRID[-1] - CUSP) / B))
    assert math.exp(logsumexp(L + axis.log_weights(L))) == pytest.approx(exact, rel=1e-12)
    cells = np.diff(np.concatenate([[GRID[0]], (GRID[1:] + GRID[:-1]) / 2, [GRID[-1]]]))
    assert abs(np.exp(L) @ cells / exact - 1) > 0.05


@pytest.mark.parametrize("log", [False, True])
def test_a_smooth_density_converges_at_second_order(log):
    """A Gaussian in x (x = log site where the axis is in log): the error of the integral falls 4x
    when the step halves (the trapezoid rule on L: O(step^2) overall), observed order 2 +- 0.1."""
    errors = []
    for n in (25, 49, 97):
        x = np.linspace(-6.0, 6.0, n)
        axis = GridAxis("s", np.exp(x) if log else x, log=log)
        L = -x**2 / 2
        errors.append(abs(math.exp(logsumexp(L + axis.log_weights(L))) / math.sqrt(2 * math.pi) - 1))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(orders, 2.0, atol=0.1)


def test_draws_follow_the_interpolated_density():
    """Draws from every point's share (counts in proportion to the weights) are draws of the
    interpolated density, here the exact cusp: a Kolmogorov-Smirnov test at 30,000 draws does not
    reject it at 1e-3 (a false alarm once in 1,000 seeds), and does reject the same points spread
    uniformly over each point's midpoint cell."""
    axis = GridAxis("d", GRID)
    L = cusp(GRID)
    weights = np.exp(L + axis.log_weights(L))
    counts = np.round(30000 * weights / weights.sum()).astype(int)
    generator = torch.Generator().manual_seed(0)
    draws = np.concatenate([axis.draw(i, L, int(c), generator).numpy() for i, c in enumerate(counts) if c])
    assert draws.min() >= GRID[0] and draws.max() <= GRID[-1]
    total = 2 - math.exp(-(CUSP - GRID[0]) / B) - math.exp(-(GRID[-1] - CUSP) / B)

    def cdf(x):
        below = np.exp(-(CUSP - np.minimum(x, CUSP)) / B) - math.exp(-(CUSP - GRID[0]) / B)
        above = 1 - np.exp(-(np.maximum(x, CUSP) - CUSP) / B)
        return (below + above) / total

    assert stats.kstest(draws, cdf).pvalue > 1e-3
    edges = np.concatenate([[GRID[0]], (GRID[1:] + GRID[:-1]) / 2, [GRID[-1]]])
    rng = np.random.default_rng(0)
    uniform = np.concatenate([rng.uniform(edges[i], edges[i + 1], c) for i, c in enumerate(counts)])
    assert stats.kstest(uniform, cdf).pvalue < 1e-6


def test_a_log_axis_draws_inside_its_cell_in_log():
    """A point's draws lie between the geometric midpoints to its neighbours, on both sides."""
    axis = GridAxis("tau", np.geomspace(0.01, 1.0, 5), log=True)
    L = np.array([-3.0, -1.0, 0.0, -2.0, -40.0])
    values = axis.draw(2, L, 1000, torch.Generator().manual_seed(0)).numpy()
    lo, hi = np.sqrt(axis.grid[1] * axis.grid[2]), np.sqrt(axis.grid[2] * axis.grid[3])
    assert lo * (1 - 1e-12) <= values.min() < axis.grid[2] < values.max() <= hi * (1 + 1e-12)


@pytest.mark.parametrize("grid, log, match", [([0.1, 0.2], False, "increasing"), ([0.2, 0.1, 0.3], False, "increasing"),
                                              ([0.1, np.nan, 0.3], False, "finite"), ([-0.1, 0.1, 0.3], True, "positive")])
def test_bad_grids_are_refused(grid, log, match):
    with pytest.raises(ValueError, match=match):
        GridAxis("s", grid, log=log)
