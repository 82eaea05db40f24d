"""``bayespd.materials.checks``: moduli from (E, nu) in closed form, and the modulus check that
every law applies (scalar or per-particle, finite, positive) with its error types."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.materials import NonFiniteParameterError, ParameterRangeError, check_modulus


@pytest.mark.parametrize("E,nu", [(4000.0, 0.3), (1.0, 0.0), (2.5, -0.5), (70e9, 0.499)])
def test_moduli_from_young_closed_forms_and_their_inverse(E, nu):
    """K = E / (3 (1 - 2 nu)), G = E / (2 (1 + nu)); and back: E = 9 K G / (3 K + G),
    nu = (3 K - 2 G) / (2 (3 K + G)), to rounding."""
    K, G = (float(v) for v in bp.moduli_from_young(E, nu))
    assert K == pytest.approx(E / (3 * (1 - 2 * nu)), rel=1e-15)
    assert G == pytest.approx(E / (2 * (1 + nu)), rel=1e-15)
    assert 9 * K * G / (3 * K + G) == pytest.approx(E, rel=1e-12)
    assert (3 * K - 2 * G) / (2 * (3 * K + G)) == pytest.approx(nu, abs=1e-12)


def test_moduli_from_young_on_fields():
    E, nu = torch.linspace(1.0, 2.0, 5), torch.tensor([0.1, 0.2, 0.25, 0.3, 0.4])
    K, G = bp.moduli_from_young(E, nu)
    assert K.shape == G.shape == (5,)
    torch.testing.assert_close(K, E / (3 * (1 - 2 * nu)), rtol=1e-15, atol=0)
    torch.testing.assert_close(G, E / (2 * (1 + nu)), rtol=1e-15, atol=0)


# moved from tests/test_stability.py (nu >= 1/2) and tests/test_validation.py (nu = -1 as well)
@pytest.mark.parametrize("nu", [0.5, 0.5001, 0.7, -1.0])
def test_poisson_ratio_at_or_above_half_is_refused_with_the_fix(nu):
    with pytest.raises(ValueError, match=r"\(-1, 0.5\).*infinite.*use nu < 0.5"):
        bp.moduli_from_young(1.0, nu)


@pytest.mark.parametrize("E", [0.0, -1.0, float("nan"), float("inf"), [1.0, -1.0]])
def test_non_positive_or_non_finite_young_modulus_is_refused(E):
    with pytest.raises(ValueError, match="E must be finite and positive"):
        bp.moduli_from_young(E, 0.3)


@pytest.mark.parametrize("value", [2.0, torch.tensor(2.0), torch.full((4,), 2.0), np.arange(1.0, 5.0)])
def test_check_modulus_passes_scalars_and_fields_unchanged(value):
    v = check_modulus("K", value, 4)
    assert torch.equal(v.expand(4), torch.as_tensor(value, dtype=v.dtype).expand(4))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf"), [1.0, float("nan"), 1.0]])
def test_check_modulus_refuses_non_finite_values(bad):
    with pytest.raises(NonFiniteParameterError, match="K contains NaN or inf: pass finite moduli"):
        check_modulus("K", bad, 3)


@pytest.mark.parametrize("bad", [0.0, -1.0, [1.0, 0.0, 2.0], [1.0, 2.0, -1e-300]])
def test_check_modulus_refuses_non_positive_values(bad):
    with pytest.raises(ParameterRangeError, match=r"G must be positive.*log scale") as err:
        check_modulus("G", bad, 3)
    assert not isinstance(err.value, NonFiniteParameterError)


@pytest.mark.parametrize("shape", [(2,), (4,), (3, 1), (1, 3)])
def test_check_modulus_refuses_fields_of_the_wrong_shape(shape):
    with pytest.raises(ValueError, match=r"K must be a scalar or have one value per particle \(3\)") as err:
        check_modulus("K", torch.ones(shape), 3)
    assert not isinstance(err.value, ParameterRangeError)


def test_the_error_types_nest():
    """A sampler treats a ParameterRangeError as a rejected proposal; NaN or inf is one."""
    assert issubclass(NonFiniteParameterError, ParameterRangeError)
    assert issubclass(ParameterRangeError, ValueError)


# moved from tests/test_stability.py: a law checks its moduli through check_modulus
def test_infinite_bulk_modulus_is_refused():
    p = bp.grid_2d(6, 6, 1.0)
    with pytest.raises(NonFiniteParameterError, match="finite moduli"):
        bp.LPS(p, bp.find_bonds(p, 2.0), plane="strain").numeric_stiffness({"K": float("inf"), "G": 1.0, "delta": 2.0})


@pytest.mark.parametrize("E,nu", [(4000.0, 0.3), (1.0, 0.0), (2.5, -0.5), (70e9, 0.499), (3.0, 0.37)])
@pytest.mark.parametrize("plane", [None, "stress", "strain"])
def test_young_from_moduli_is_the_exact_inverse(E, nu, plane):
    """(E, nu) -> (K, G) -> (E, nu) to a few ulps (condition 1 / (1 - 2 nu) at nu = 0.499),
    and (K, G) -> (E, nu) -> (K, G); the same answer for every plane (K is the 3D modulus)."""
    E2, nu2 = (float(v) for v in bp.young_from_moduli(*bp.moduli_from_young(E, nu), plane=plane))
    assert E2 == pytest.approx(E, rel=1e-13) and nu2 == pytest.approx(nu, abs=1e-14)
    K, G = (float(v) for v in bp.moduli_from_young(E, nu))
    K2, G2 = (float(v) for v in bp.moduli_from_young(*bp.young_from_moduli(K, G, plane=plane)))
    assert K2 == pytest.approx(K, rel=1e-12) and G2 == pytest.approx(G, rel=1e-14)


def test_young_from_moduli_on_fields_and_against_the_plane_stress_kappa():
    """kappa_stress = 9 K G / (3 K + 4 G) = E / (2 (1 - nu)): the in-plane modulus of LPS."""
    K, G = torch.tensor([1.0, 2.0, 5.0]), torch.tensor([0.5, 1.5, 1.0])
    E, nu = bp.young_from_moduli(K, G, plane="stress")
    assert E.shape == nu.shape == (3,)
    p = bp.grid_2d(4, 4, 1.0)
    kappa = bp.LPS(p, bp.find_bonds(p, 2.0), plane="stress").kappa(K, G)
    torch.testing.assert_close(kappa, E / (2 * (1 - nu)), rtol=1e-14, atol=0)


@pytest.mark.parametrize("K,G,plane,match", [(-1.0, 1.0, None, r"K must be positive.*3D bulk modulus"),
                                             (1.0, float("nan"), None, r"G contains NaN.*shear modulus"),
                                             (1.0, 1.0, "3d", r"plane must be one of.*3D bulk modulus")])
def test_young_from_moduli_refuses_bad_input_by_name(K, G, plane, match):
    with pytest.raises(ValueError, match=match):
        bp.young_from_moduli(K, G, plane=plane)
