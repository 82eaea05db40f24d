import numpy as np
import pytest

from bayespd.inverse.stopping import Monitor, Stop, projected_gradient


def test_the_projected_gradient_vanishes_at_a_kkt_point_only():
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 1.0])
    # on the lower bound with the gradient pushing outward: a KKT point
    assert projected_gradient(np.array([0.0, 0.5]), np.array([3.0, 0.0]), lo, hi) == 0.0
    # the same gradient pointing inward is not
    assert projected_gradient(np.array([0.0, 0.5]), np.array([-0.25, 0.0]), lo, hi) == 0.25
    # without bounds it is the gradient's max-norm
    g = np.array([0.3, -0.7])
    assert projected_gradient(np.zeros(2), g, -np.inf, np.inf) == pytest.approx(0.7, abs=0)


def test_a_stall_stops_unconverged_after_exactly_stall_evaluations():
    m = Monitor(ftol=1e-3, maxfun=100, stall=3)
    m.evaluated([0.0], 1.0)
    m.evaluated([1.0], 0.9995)          # lower, but by < ftol: counts toward the stall
    m.evaluated([2.0], 0.9999)
    with pytest.raises(Stop, match="stalled: 3 evaluations") as stop:
        m.evaluated([3.0], 0.9994)
    assert not stop.value.converged
    assert m.best_J == 0.9994 and m.best_z.tolist() == [3.0]


def test_progress_resets_the_stall_and_maxfun_ends_the_run():
    m = Monitor(ftol=1e-3, maxfun=4, stall=2)
    for k, J in enumerate([1.0, 0.5, 0.25]):
        m.evaluated([k], J)
    with pytest.raises(Stop, match="maxfun=4") as stop:
        m.evaluated([3], 0.1)
    assert not stop.value.converged and m.evaluations == 4


def test_a_small_relative_decrease_is_convergence_but_no_decrease_is_not():
    m = Monitor(ftol=1e-6, maxfun=100, stall=10)
    m.iteration(2.0)
    m.iteration(1.0)                     # halved: go on
    m.iteration(1.0)                     # no decrease: the stall test judges, not this one
    with pytest.raises(Stop, match="relative decrease") as stop:
        m.iteration(1.0 - 5e-7)
    assert stop.value.converged


@pytest.mark.parametrize("z", [[0.0, np.inf], [np.nan], [-700.5]])
def test_a_proposal_no_parameter_can_take_stops_before_it_is_evaluated(z):
    """L-BFGS-B with round-off-spoilt curvature pairs stepped to z = inf under CHOLMOD (CI):
    the run must end at its best point, unconverged, not raise from inside the model."""
    m = Monitor(ftol=1e-3, maxfun=100, stall=3)
    m.evaluated([0.0], 1.0)
    with pytest.raises(Stop, match="NaN or beyond") as stop:
        m.proposed(np.array(z))
    assert not stop.value.converged and m.best_z.tolist() == [0.0]
    m.proposed(np.array([699.0, -699.0]))  # representable: no stop
