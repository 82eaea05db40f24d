"""bayespd/ensemble/scene.py: the FractureScene's checks and normalisation, the outcomes read
from a run, and errors of a realisation returned (batch) or raised (one)."""
import numpy as np
import pytest
import torch

from bayespd.ensemble.scene import FractureScene, _outcomes, realise, realise_batch
from bayespd.solvers.fracture import Realisation


def test_bad_input_names_the_fix():
    with pytest.raises(ValueError, match="origin and direction must be 2D"):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), direction=(0.0, 0.0))
    with pytest.raises(ValueError, match="dt must be positive"):
        FractureScene(print, ("K",), [1.0], 0.0, np.zeros((3, 2)))
    with pytest.raises(ValueError, match='"exact" or "lagged"'):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), tangent="secant")
    with pytest.raises(ValueError, match="build must be a callable"):
        FractureScene(None, ("K",), [1.0], 1.0, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="load_factors must be a non-empty 1D"):
        FractureScene(print, ("K",), [1.0, np.nan], 1.0, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="threshold must lie in"):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), threshold=1.0)
    with pytest.raises(ValueError, match=r"\(N, 2\) particle positions"):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="zone must be a mask of the 3 particles"):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), zone=[True, False])


def test_inputs_are_normalised():
    """direction becomes a unit vector, load factors and x float64 arrays, params a tuple and
    zone a boolean mask."""
    scene = FractureScene(print, ["K", "s0"], [1, 2, 3], 0.5, [[0, 0], [1, 0]], direction=(3.0, 4.0), zone=[1, 0])
    assert scene.direction == pytest.approx((0.6, 0.8), rel=1e-15) and scene.params == ("K", "s0")
    assert scene.load_factors.dtype == np.float64 and scene.x.dtype == np.float64
    assert scene.zone.dtype == bool and scene.zone.tolist() == [True, False]


def run(reaction, crack_length, broken, load_factor=None):
    n = len(reaction)
    return Realisation(t=np.arange(n) * 0.5, load_factor=np.arange(1.0, n + 1) if load_factor is None else load_factor,
                       reaction=np.asarray(reaction, float), broken=np.asarray(broken), crack_length=np.asarray(crack_length),
                       phi=np.zeros(4), path=np.array([[0.0, 0.0], [3.0, 4.0]]), u=torch.zeros(4, 2),
                       intact=torch.ones(3), seed=1)


def test_outcomes_of_a_run():
    """Peak load: the largest |R| (or the chosen component, sign kept) and its load factor;
    failure: the load factor where the crack first reaches failure_length (NaN if never);
    first failure time: t of the first step with a broken bond; final crack length: the
    path's length (a 3-4-5 segment: 5)."""
    scene = FractureScene(print, ("K",), [1.0], 1.0, np.zeros((4, 2)), failure_length=2.0)
    r = run([[3.0, 4.0], [0.0, -6.0], [1.0, 1.0]], [0.0, 1.0, 2.5], [0, 2, 5])
    out = _outcomes(scene, r)
    assert out["peak_load"] == 6.0 and out["peak_load_factor"] == 2.0
    assert out["failure_load_factor"] == 3.0 and out["first_failure_time"] == 0.5
    assert out["final_crack_length"] == pytest.approx(5.0, rel=1e-15)
    assert out["reaction"].dtype == np.float64 and out["broken"].dtype == np.int64
    along_y = FractureScene(print, ("K",), [1.0], 1.0, np.zeros((4, 2)), load_component=1, failure_length=9.0)
    out = _outcomes(along_y, run([[3.0, 4.0], [0.0, -6.0], [1.0, 1.0]], [0.0, 1.0, 2.5], [0, 0, 0]))
    assert out["peak_load"] == -6.0 and np.isnan(out["failure_load_factor"]) and np.isnan(out["first_failure_time"])


def failing_build(params):
    raise ArithmeticError(f"no body for K={params['K']}")


def test_a_failed_realisation_is_returned_in_a_batch_and_raised_alone():
    scene = FractureScene(failing_build, ("K",), [1.0], 1.0, np.zeros((3, 2)))
    assert realise_batch(scene, []) == []
    threads = torch.get_num_threads()
    (out,) = realise_batch(scene, [({"K": 2.0, "unused": 1.0}, 0)])
    assert isinstance(out, ArithmeticError) and str(out) == "no body for K=2.0"
    with pytest.raises(ArithmeticError, match="no body for K=3.0"):
        realise(scene, {"K": 3.0}, 1)
    assert torch.get_num_threads() == threads  # restored


def test_path_threshold_is_a_damage_index():
    with pytest.raises(ValueError, match=r"path_threshold must lie in \(0, 1\), got 1.5: it is a damage index"):
        FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), path_threshold=1.5)
