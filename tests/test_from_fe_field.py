"""experiments/from_fe_field.py's own piece: the term against a known reference (inside and
outside the measured body), with and without the peer's mesh error."""
import sys
from pathlib import Path

import numpy as np
import torch

import bayespd as bp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
from from_fe_field import fe_error_term  # noqa: E402

POINTS = np.stack([np.linspace(0.0, 9.0, 10), np.zeros(10)], 1)
T = torch.linspace(1.0, 2.0, 20, dtype=torch.float64).reshape(10, 2)


class StandIn:
    """A scene stand-in: predict = T (1 + G / K) / K (delta recorded), observed at POINTS."""

    material = particles = None
    param_names = ("K", "G", "delta")
    observation = type("Obs", (), {"points": torch.as_tensor(POINTS)})()

    def __init__(self):
        self.seen = []

    def predict(self, params):
        self.seen.append(float(params["delta"]))
        K, G = (torch.as_tensor(params[k], dtype=torch.float64) for k in ("K", "G"))
        return T * (1 + G / K) / K

    def diagnostics(self, draws):
        return {"delta_seen": draws["delta"]}


def test_term_of_a_scaled_reference_inside_the_body_only():
    """reference = 1.1 model at the points inside (x < 5), no data outside: the relative error is
    0.1 T / rms(T) inside and 0 outside at every nu (the model's shape does not change with nu),
    so the smooth trend is that constant and the covariance vanishes."""
    scene = bp.Held(StandIn(), delta=3.0)
    inside = lambda x: x[:, 0] < 5  # noqa: E731

    def fe_at(E, nu, points):
        K, G = bp.moduli_from_young(E, nu)
        assert len(points) == 5
        return 1.1 * scene.predict({"K": float(K), "G": float(G)})[:5].numpy()

    term = fe_error_term(fe_at, scene, np.linspace(0.15, 0.45, 16), inside)
    expected = 0.1 * T / T.square().mean().sqrt()
    expected[5:] = 0.0
    assert torch.allclose(term.mean, expected, rtol=0, atol=1e-12)
    assert float(term.covariance().abs().max()) < 1e-20


def test_term_with_the_peers_mesh_error():
    """A coarse peer 0.99 x the fine one inside: the mesh error 0.011 T / rms(T) inside (0 outside)
    at every nu enters as its second moment (rank one, plus its mean square on the diagonal with
    ``spread``); the trend is that of the fine peer alone."""
    scene = bp.Held(StandIn(), delta=3.0)
    inside = lambda x: x[:, 0] < 5  # noqa: E731

    def fe_at(E, nu, points, factor=1.1):
        K, G = bp.moduli_from_young(E, nu)
        return factor * scene.predict({"K": float(K), "G": float(G)})[:5].numpy()

    nus = np.linspace(0.15, 0.45, 16)
    plain = fe_error_term(fe_at, scene, nus, inside)
    term = fe_error_term(fe_at, scene, nus, inside, fe_coarse=lambda E, nu, x: fe_at(E, nu, x, 1.1 * 0.99))
    error = 0.011 * T / T.square().mean().sqrt()
    error[5:] = 0.0
    e = error.reshape(-1, 1)
    assert torch.allclose(term.mean, plain.mean, rtol=0, atol=1e-12)
    assert torch.allclose(term.covariance(), e @ e.T + e.square().mean() * torch.eye(20), rtol=0, atol=1e-12)
