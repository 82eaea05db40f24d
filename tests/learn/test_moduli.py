"""The MD sheet's long-wave moduli (bayespd.learn.moduli) from an exact continuum response."""
import numpy as np
import pytest
import xarray as xr

from bayespd.learn.moduli import long_wave_moduli, wave_modulus

LAM, MU = 3.0, 5.0
BOX = np.array([30.0, 28.0])


def atoms(n=40):
    g = [(np.arange(n) + 0.3) * L / n for L in BOX]
    return np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 2)


def response(x, n1, n2, axis, amplitude=1e-3):
    """Forces per atom and the exact static displacement of a 2D elastic sheet (module docstring)."""
    k = 2 * np.pi * np.array([n1, n2]) / BOX
    modulus = LAM + 2 * MU if (n1, n2)[1 - axis] == 0 else MU  # k along the load, or across it
    c = np.cos(x @ k)
    B, U = np.zeros_like(x), np.zeros_like(x)
    B[:, axis] = amplitude * c * BOX.prod() / len(x)
    U[:, axis] = amplitude * c / (modulus * (k @ k))
    return U, B


def test_wave_modulus_of_an_elastic_sheet_is_exact():
    x = atoms()
    for n1, n2, axis, expected in [(1, 0, 0, LAM + 2 * MU), (0, 1, 0, MU), (0, 3, 1, LAM + 2 * MU), (2, 0, 1, MU)]:
        U, B = response(x, n1, n2, axis)
        assert wave_modulus(x, U, B, BOX, n1, n2, axis) == pytest.approx(expected, rel=1e-12)


def test_long_wave_moduli_from_a_record():
    x = atoms()
    cases = [(1, 0, 0), (0, 1, 0), (1, 0, 1), (0, 1, 1), (2, 0, 0)]
    U, B = zip(*(response(x, *c) for c in cases))
    ds = xr.Dataset({"X": (("atom", "dim"), x), "U": (("frame", "atom", "dim"), np.array(U)),
                     "B": (("frame", "atom", "dim"), np.array(B)),
                     "case": (("frame",), [f"sin n1={a} n2={b} axis={c}" for a, b, c in cases])},
                    attrs={"periodic": 1, "box": BOX})
    m = long_wave_moduli(ds)
    assert m["mu"] == pytest.approx(MU, rel=1e-12) and m["lambda"] == pytest.approx(LAM, rel=1e-11)
    with pytest.raises(ValueError, match="n = 1 sinusoidal loads"):
        long_wave_moduli(ds.isel(frame=[0, 4]))
