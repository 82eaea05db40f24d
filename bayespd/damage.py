"""Bond damage laws, the per-particle damage index and crack geometry from damage.

A damage law is optional in a scene; each keeps one tensor of state per bond:

    state = law.init(n_bonds)
    state = law.update(state, stretch, dt)   # after each step, stretch from NonlinearBonds.stretch
    mu = law.intact(state)                   # intact fraction per bond in [0, 1] -> force(u, ..., mu)

``CriticalStretch`` and ``SmoothStep`` keep the history maximum of the stretch (the reference
configuration counts as stretch 0); ``DamageODE`` keeps z = logit(alpha).
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from bayespd import bond_loops


def _positive(name, value):
    v = torch.as_tensor(value)
    if not bool(torch.all(torch.isfinite(v) & (v > 0))):
        raise ValueError(f"{name} must be finite and positive")
    return value


class CriticalStretch:
    """Sharp, irreversible critical stretch (Dodwell 2019 eq 2): mu = 1 while max_t s < s0, then 0
    for ever. ``s0`` is a scalar or one value per bond."""

    def __init__(self, s0):
        self.s0 = _positive("the critical stretch s0", s0)

    def init(self, n_bonds: int) -> torch.Tensor:
        return torch.zeros(n_bonds)

    def update(self, state, stretch, dt=None) -> torch.Tensor:
        """History maximum of the stretch (dt is not used)."""
        return torch.maximum(state, stretch)

    def intact(self, state) -> torch.Tensor:
        """1 where max_t s < s0, else 0, written as floats by the comparison itself (a bool
        tensor converted with ``.to`` is slower)."""
        return torch.lt(state, self.s0, out=torch.empty_like(state))


class SmoothStep(CriticalStretch):
    """gamma = (1 - tanh((max_t s - s0) / eta)) / 2 (You 2023 eq 3.10): irreversible,
    differentiable in s0 and eta, the sharp law as eta -> 0."""

    def __init__(self, s0, eta):
        super().__init__(s0)
        self.eta = _positive("the smoothing width eta", eta)

    def intact(self, state) -> torch.Tensor:
        return 0.5 * (1 - torch.tanh((state - self.s0) / self.eta))


class DamageODE:
    """Damage ODE of Dodwell 2019 §2.1, with the rate lam that the paper lists but does not print:

        d alpha / dt = -lam exp(k s) alpha^n (1 - alpha)^m,   0 < alpha(0) = alpha0 < 1,

    mu = alpha (eq 5: f = c alpha s; eq 5's expansion substitutes alpha(t) = alpha0 - int ...
    and repeats the factor alpha, which would contradict f = c alpha s in the same line).
    alpha = 1 is a rest point for m > 0, so an intact bond never starts to break: the paper
    requires alpha(0) < 1, an initial flaw, here ``alpha0``. lam = exp(-k s_c) writes the rate
    as exp(k (s - s_c)) with an activation stretch s_c. The rate is positive at s = 0: bonds
    degrade slowly even unloaded, as printed.

    Integration: with the damage clock tau = int lam exp(k s) dt, alpha(tau) solves the
    autonomous dA/dtau = -A^n (1 - A)^m, and z = logit(alpha) obeys dz/dtau = -g(z),
    g = sigmoid(z)^(n-1) sigmoid(-z)^(m-1). Over a step the stretch is frozen at the value
    passed (the end of the step: first order in dt for a varying stretch). For n = m = 1
    (logistic) g = 1 and the update z -= lam exp(k s) dt is exact,
    alpha = alpha0 / (alpha0 + (1 - alpha0) e^tau). Otherwise ``substeps`` classical RK4
    steps in z: fourth order while lam e^(k s) dt max(n - 1, |m - 1|) / substeps <~ 1, and for
    any step stable: every stage slope is negative, so z never increases and alpha stays in
    [0, 1) (larger steps lose accuracy, not stability). n >= 1 is required: for n < 1 alpha
    reaches 0 in finite time (z -> -inf).
    """

    def __init__(self, *, k, alpha0: float, lam=1.0, n=1.0, m=1.0, substeps: int = 4):
        if not 0 < alpha0 < 1:
            raise ValueError("alpha0 must lie in (0, 1): alpha = 1 is a rest point of the ODE "
                             "(no damage ever starts), alpha = 0 is a broken bond")
        k_ = torch.as_tensor(k)
        if not bool(torch.all(torch.isfinite(k_) & (k_ >= 0))):
            raise ValueError("k must be finite and non-negative (Dodwell 2019: positive constants)")
        if not float(torch.as_tensor(n).min()) >= 1:
            raise ValueError("n must be >= 1: for n < 1 alpha reaches 0 in finite time")
        if not (int(substeps) == substeps and substeps >= 1):
            raise ValueError("substeps must be a positive integer")
        self.k, self.alpha0 = k, float(alpha0)
        self.lam, self.n, self.m = _positive("lam", lam), n, _positive("m", m)
        self.substeps = int(substeps)
        self._logistic = not any(torch.is_tensor(v) for v in (n, m)) and n == 1 and m == 1

    def init(self, n_bonds: int) -> torch.Tensor:
        return torch.full((n_bonds,), float(np.log(self.alpha0 / (1 - self.alpha0))))

    def _g(self, z):
        return torch.exp((self.n - 1) * torch.nn.functional.logsigmoid(z)
                         + (self.m - 1) * torch.nn.functional.logsigmoid(-z))

    def update(self, state, stretch, dt=None) -> torch.Tensor:
        if dt is None or not float(dt) > 0:
            raise ValueError("the damage ODE needs a positive time step dt")
        tau = self.lam * torch.exp(self.k * stretch) * dt
        if self._logistic:
            return state - tau
        h, z = tau / self.substeps, state
        for _ in range(self.substeps):
            k1 = self._g(z)
            k2 = self._g(z - 0.5 * h * k1)
            k3 = self._g(z - 0.5 * h * k2)
            k4 = self._g(z - h * k3)
            z = z - h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return z

    def intact(self, state) -> torch.Tensor:
        return torch.sigmoid(state)


def damage_index(particles, bonds, intact, weight=None) -> torch.Tensor:
    """phi_i = 1 - sum_j w mu V_j / sum_j w V_j over particle i's bonds (w = 1 when ``weight``
    is None, else e.g. ``material.bond_weight(params)``); differentiable in mu."""
    return DamageIndex(particles, bonds, weight)(intact)


class DamageIndex:
    """``damage_index`` for one body, its denominator sum_j w V_j taken once: phi_i is
    evaluated as sum_j w (1 - mu) V_j / sum_j w V_j, over the damaged bonds only (mu < 1)
    unless mu requires a gradient, by torch (O(damaged bonds) after a pass that finds them)
    or by one compiled pass (``bond_loops.damage_sums``)."""

    def __init__(self, particles, bonds, weight=None):
        self.n = particles.n
        self.i, self.j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
        self.V = torch.as_tensor(particles.volume)
        self.w = torch.ones(len(self.i), dtype=self.V.dtype) if weight is None else torch.as_tensor(weight)
        self.total = self._family(self.w, slice(None))
        if bool(torch.any(self.total == 0)):
            raise ValueError("a particle has no weighted bonds: its damage index is undefined")

    def _family(self, x, bonds):
        i, j, V = self.i[bonds], self.j[bonds], self.V
        return torch.zeros(self.n, dtype=x.dtype).index_add(0, i, x * V[j]).index_add(0, j, x * V[i])

    def __call__(self, intact) -> torch.Tensor:
        mu = torch.as_tensor(intact)
        if bond_loops.usable(mu, self.w, self.V):  # one compiled pass, the same sums in the same order
            return bond_loops.damage_sums(self.i, self.j, self.w, mu, self.V) / self.total
        bonds = slice(None) if mu.requires_grad else torch.nonzero(mu < 1).reshape(-1)
        return self._family(self.w[bonds] * (1 - mu[bonds]), bonds) / self.total


def broken(intact, level: float = 0.5) -> torch.Tensor:
    """Mask of the broken bonds: intact fraction below ``level``."""
    return torch.as_tensor(intact) < level


def crack_path(particles, phi, threshold: float = 0.4, width: float | None = None) -> np.ndarray:
    """The crack as an ordered polyline (k, dim) through the damaged particles.

    Particles with phi > threshold are linked when closer than 1.5 h; the largest cluster is
    projected on its principal direction (phi-weighted covariance) and cut into bins of
    ``width`` (default 2h) along it. A point sits at each bin's centre along the direction and
    at the phi-weighted mean offset of its particles across it (so lattice noise moves points
    only across the crack); the two end points sit at the outermost particles' projections
    pushed out by h/2 (their half cells). Simple and robust for a crack that is a graph over
    its principal direction; a kink beyond 90 degrees or a branch is averaged over. Bins of h
    alias with the lattice on a slanted crack (offsets jump by ~h/2 from bin to bin, +15 % of
    length at 30 degrees); 2h keeps the length within h.
    """
    x = np.asarray(particles.x)
    phi = np.asarray(torch.as_tensor(phi).detach())
    h = particles.h
    width = float(width or 2 * h)
    idx = np.flatnonzero(phi > threshold)
    if len(idx) < 2:
        return np.zeros((0, x.shape[1]))
    pairs = cKDTree(x[idx]).query_pairs(1.5 * h, output_type="ndarray")
    labels = bond_loops.components(len(idx), pairs[:, 0], pairs[:, 1])[1]
    keep = idx[labels == np.argmax(np.bincount(labels))]
    pts, w = x[keep], phi[keep]
    centre = np.average(pts, axis=0, weights=w)
    axes = np.linalg.eigh(((pts - centre) * w[:, None]).T @ (pts - centre))[1]
    direction, normals = axes[:, -1], axes[:, :-1]
    t, s = (pts - centre) @ direction, (pts - centre) @ normals
    bins = np.round((t - t.min()) / width).astype(np.int64)
    mass = np.bincount(bins, weights=w)
    used = np.flatnonzero(mass > 0)
    used = np.repeat(used, 2) if len(used) == 1 else used
    along = t.min() + width * used.astype(float)
    along[0], along[-1] = t.min() - h / 2, t.max() + h / 2
    across = np.stack([np.bincount(bins, weights=w * s[:, a])[used] for a in range(s.shape[1])], 1)
    across /= mass[used][:, None]
    return centre + along[:, None] * direction + across @ normals.T


def crack_length(path: np.ndarray) -> float:
    """Length of a polyline (k, dim)."""
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
