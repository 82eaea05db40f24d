"""bayespd/reference/plate_with_hole.py: the plate with a hole as a PD scene and its FE peer.

The FE peer is checked against classical elasticity on a long plate (hole 3.9 W from either
end, so Saint-Venant end effects are below 1e-3): the stress concentration at the hole against
Howland's series solution for a hole in a strip, as fitted by Heywood, Kt_net = 2 + (1 - d/W)^3
(within 0.1 % of Howland's 2.51 at d/W = 0.2; Pilkey, Peterson's Stress Concentration
Factors, chart 4.1), and the uniform strain F / (W t E) far from the hole.
"""
import numpy as np
import pytest

pytest.importorskip("skfem")

from bayespd.reference import observed_order, pd_versus_fe  # noqa: E402
from bayespd.reference import plate_with_hole as ph  # noqa: E402

LONG = ph.Geometry(length=160.0, width=20.0, radius=2.0)


def heywood_gross(g: ph.Geometry) -> float:
    ratio = 2 * g.radius / g.width
    return (2 + (1 - ratio) ** 3) / (1 - ratio)


def kt(h: float) -> float:
    return ph.hole_stress(ph.fe_solution(h, geometry=LONG), geometry=LONG) / LONG.nominal_stress()


def test_stress_concentration_matches_howland():
    """Q2 on the graded O-grid: Kt = 3.163 at h = 1 against Heywood's 3.140 (measured +0.7 %;
    at h = 0.5, +0.5 %). The tolerance 1 % covers the 0.1 % of the fit and the O(h^2) error
    of the polygonal hole (its sagitta 1e-3 R at h = 1)."""
    assert kt(1.0) == pytest.approx(heywood_gross(LONG), rel=0.01)


def test_far_field_strain_is_uniaxial():
    """At x = 40 mm (34 mm from the clamp, 40 from the hole) eps_xx = F / (W t E) and
    eps_yy = -nu eps_xx (measured 1.9e-4 and 1.1e-3 off: the clamp's restraint of the lateral
    contraction decays as exp(-pi x / W) ~ 5e-3, times nu)."""
    fe = ph.fe_solution(2.0, geometry=LONG)
    d = 0.5
    u = fe.at(np.array([[40 - d, 10.0], [40 + d, 10.0], [40, 10 - d], [40, 10 + d]]))
    strain = LONG.nominal_stress() / ph.YOUNG
    assert (u[1, 0] - u[0, 0]) / (2 * d) == pytest.approx(strain, rel=5e-4)
    assert (u[3, 1] - u[2, 1]) / (2 * d) == pytest.approx(-ph.POISSON * strain, rel=2e-3)


@pytest.mark.slow
def test_stress_concentration_converges_at_second_order():
    """Kt at h = 2, 1, 0.5: successive changes shrink 3.3x (measured; order 1.7 against the
    2 of the polygon's sagitta and of Q2 stresses)."""
    k = [kt(h) for h in (2.0, 1.0, 0.5)]
    assert abs(k[0] - k[1]) / abs(k[1] - k[2]) > 2.5
    assert k[2] == pytest.approx(heywood_gross(LONG), rel=0.007)


def test_mesh_covers_the_plate_minus_the_hole():
    """Cell areas sum to L W - (the inscribed polygon's area): every cell counter-clockwise, no
    overlaps or gaps."""
    h = 1.0
    mesh = ph.hole_mesh(h)
    p = mesh.p[:, mesh.t]
    d1, d2 = p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]
    area = 0.5 * (d1[0] * d2[1] - d1[1] * d2[0])
    on_hole = mesh.p[:, np.abs(np.linalg.norm(mesh.p.T - ph.PLATE.centre, axis=1) - ph.PLATE.radius) < 1e-9]
    angle = np.sort(np.arctan2(on_hole[1] - ph.PLATE.centre[1], on_hole[0] - ph.PLATE.centre[0]))
    polygon = 0.5 * ph.PLATE.radius**2 * np.sin(np.diff(np.append(angle, angle[0] + 2 * np.pi))).sum()
    assert len(angle) >= 4 * round(ph.PLATE.width / h)
    assert area.min() > 0
    assert area.sum() == pytest.approx(ph.PLATE.length * ph.PLATE.width - polygon, rel=1e-12)


def test_pd_plate_converges_to_the_fe_peer():
    """LPS, m = 3, against the h = 0.5 peer 3 mm from the clamp and the load (measured 0.174
    at h = 2 and 0.071 at h = 1: at least first order in delta)."""
    fe = ph.fe_solution(0.5)
    e = [pd_versus_fe(ph, h, 3, {"iso": fe}, 3.0)["errors"]["iso"] for h in (2.0, 1.0)]
    assert e[1] < 0.08
    assert observed_order([2.0, 1.0], e) > 1.0


def test_bad_input_names_the_fix():
    with pytest.raises(ValueError, match="must divide the clamp"):
        ph.hole_mesh(0.8)
    with pytest.raises(ValueError, match="hole must fit"):
        ph.Geometry(radius=11.0)
    fe = ph.fe_solution(2.0)
    with pytest.raises(ValueError, match="outside the FE mesh"):
        fe.at(np.array([[20.0, 10.0]]))
