"""Stability on stiff and extreme cases (issue 4), fast versions of experiments/stability.py:
nu -> 0.5, a 1e6 stiffness contrast, delta/h from 1.5 to 10, a particle isolated by damage,
float32 explicit dynamics, Langevin at 100x the explicit limit. Direct solves are judged
against the forward-error bound sqrt(n) cond(A) eps of a backward-stable solve."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.nonlinear import NonlinearBonds

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import stability as st  # noqa: E402


def test_nearly_incompressible_plane_strain_is_solved_to_rounding():
    """LPS plane strain, affine patch test (the exact PD solution): the error stays below
    sqrt(n) cond(A) eps, and cond(A) grows like the volumetric stiffness K/G ~ 1/(1 - 2 nu)
    (cond (1 - 2 nu) within a factor 1.5 of its value at 0.49)."""
    rows = []
    for nu in (0.49, 0.499, 0.4999):
        K, G = (float(v) for v in bp.moduli_from_young(1.0, nu))
        rows.append(st.patch_test(bp.LPS, 3, {"K": K, "G": G}, "strain", interior=6))
        assert rows[-1]["error"] <= rows[-1]["bound"], rows[-1]
    scaled = np.array([r["cond"] * (1 - 2 * nu) for r, nu in zip(rows, (0.49, 0.499, 0.4999))])
    assert np.all(np.abs(scaled / scaled[0] - 1) < 0.5), scaled


@pytest.mark.parametrize("cls", [bp.LPS, bp.BondBased])
def test_stiffness_contrast_1e6_direct_solve_meets_the_rounding_bound(cls):
    """A bar whose moduli jump by 1e6 at mid-length, pulled at the stiff end: cond(A) grows by
    the contrast (>= 1e5 x that of the uniform bar), and the direct solve stays within
    sqrt(n) cond(A) eps of the long-double iteratively refined solution."""
    kw = {"length": 20.0, "width": 3.0, "delta": 2.0}
    uniform = st.contrast_case(1.0, cls, **kw)
    stiff = st.contrast_case(1e6, cls, **kw)
    assert stiff["cond"] > 1e5 * uniform["cond"]
    for r in (uniform, stiff):
        assert r["stable"] and r["error"] <= r["bound"], r


@pytest.mark.parametrize("m", [1.5, 2, 4, 10])
def test_horizon_ratios_from_1p5_to_10_solve_the_patch_test(m):
    """Affine patch test for delta/h = m: exact up to sqrt(n) cond eps (bond-based for all m,
    LPS for m <= 4, whose frame is 2 delta thick)."""
    r = st.patch_test(bp.BondBased, m, {"K": 1.0}, interior=6)
    assert r["error"] <= r["bound"], r
    if m <= 4:
        r = st.patch_test(bp.LPS, m, {"K": 1.0, "G": 0.6}, interior=4)
        assert r["error"] <= r["bound"], r


def test_quadratic_model_error_falls_as_the_horizon_resolves():
    """Bond-based, quadratic manufactured solution with the classical body force (exact for
    the continuum PD operator): the lattice error at m = 6 is below half that at m = 2."""
    assert st.quadratic_error(6)["error"] < 0.5 * st.quadratic_error(2)["error"]


def test_isolated_particle_needs_the_confinement_term():
    """eps = 0: refused, naming the particle and the fix. eps > 0: the isolated particle's
    dofs decouple (A = blockdiag(K_rest + eps I, eps I)), the unloaded particle stays at 0, and
    the rest differs from the eps = 0 solution by at most eps / lambda_min (first-order
    perturbation: u_eps - u_0 = -eps A_eps^-1 u_0), with slope 1 in eps."""
    mat, params, c, load, intact, k = st.isolated_body()
    F0 = bp.solvers.linear_elastic(mat, params, load, eps=0.0, constraints=c, intact=intact)
    with pytest.raises(bp.NotPositiveDefiniteError, match=rf"particle {k}\).*eps > 0"):
        F0.equilibrium()
    res = st.isolated(quick=True)
    rows = res["rows"]
    for r in rows:
        assert r["stable"] and r["isolated_displacement"] == 0.0
        assert r["error"] <= r["eps_over_lambda_min"], r
    slopes = np.diff(np.log([r["error"] for r in rows[1:]])) / np.diff(np.log([r["eps"] for r in rows[1:]]))
    np.testing.assert_allclose(slopes, 1.0, atol=0.05)


def test_isolated_particle_leaves_the_nonlinear_lps_force_finite_in_float32():
    """The LPS weighted volume of a fully broken particle is floored (materials.lps.M_FLOOR): its
    force is exactly 0 and every force is finite, in float32 as in float64."""
    mat, params, _, _, intact, k = st.isolated_body()
    kin = NonlinearBonds(mat)
    u = 1e-3 * torch.randn(mat.particles.n, 2, generator=torch.Generator().manual_seed(0))
    f64 = kin.at(params).force(u, intact)
    f32 = kin.at(params, torch.float32).force(u.float(), intact)
    assert torch.isfinite(f32).all() and float(f32[k].abs().max()) == 0.0
    assert float((f32.double() - f64).norm() / f64.norm()) < 50 * st.EPS32


def test_float32_explicit_dynamics_drift_is_rounding_sized():
    """Velocity Verlet with the exact PMB force in float32 and float64 from the same state
    (strain 1e-4, 2000 steps at half the critical step): the trajectory stays float32 and the
    two differ by less than n eps32 (linear accumulation of per-step rounding), in energy too;
    the float32 extension is accurate to a few eps32, where |y| - |xi| would lose 1e-3."""
    e = st.precision(quick=True)
    assert e["dtype_kept"] == "torch.float32"
    assert e["displacement_rel_diff_max"] < e["bound_n_eps32"]
    assert e["energy_gap_max_over_E0"] < e["bound_n_eps32"]
    assert e["extension_rel_error32_stable"] < 10 * st.EPS32
    assert e["extension_rel_error32_naive"] > 100 * e["extension_rel_error32_stable"]


def test_langevin_at_100x_the_explicit_limit():
    """Dodwell 2019 eq 4 on an LPS plate with eps (cond(A) ~ 70) at dt = 100x 2 eta / lambda_max:
    Euler-Maruyama is refused with the limit and the fix; theta = 1/2 samples eta A^-1: every
    mode's variance ratio within 4.5 SE (sqrt(2/B), B = 2000 i.i.d. chains; family-wise false
    alarm <= 72 x 6.8e-6) and the trace within 4.5 SE, a test that detects a uniform variance
    error of 2.5 % with power 99 %; theta = 1 follows its own (biased) chain law, which the
    same scores reject against eta A^-1."""
    f = st.langevin(quick=True)
    assert "reduce dt below" in f["euler_maruyama_refused"] and "semi_implicit" in f["euler_maruyama_refused"]
    half, one = f["theta_0.5"], f["theta_1"]
    assert half["stable"] and half["max_abs_z_vs_eta_Ainv"] < 4.5 and half["trace_z"] < 4.5, half["trace_z"]
    assert f["trace_test_detectable_error_99pct_power"] < 0.03
    assert one["max_abs_z_vs_chain_law"] < 4.5
    assert one["max_abs_z_vs_eta_Ainv"] > 20
