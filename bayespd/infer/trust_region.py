"""Trust-region Newton steps on an exact Hessian (Nocedal & Wright 2006, Algorithms 4.1 and 4.3).

``polish`` takes a point where a quasi-Newton search stopped to a mode: each step minimises the
quadratic model g.p + p.H.p / 2 over |p| <= radius (``step``, solved exactly in H's eigenbasis,
the "hard case" included), so an indefinite Hessian (a saddle, or a search that stopped early)
is followed down its negative curvature instead of ending the polish. The first step at a
positive definite Hessian is the full Newton step (the radius starts at its length), so a
converged mode is left where it is, and a plain Newton polish is what this does near a mode.
"""

import math

import torch

ETA = 0.1  # accept a step that achieves this share of the model's predicted decrease
BISECTIONS = 200  # halvings of the secular equation's bracket: far below rounding


def step(g, h, radius):
    """(p, predicted decrease): argmin of g.p + p.H.p / 2 over |p| <= radius, p = -(H + lam I)^-1 g
    with lam >= max(0, -lambda_min) (Alg. 4.3); where g has no component along the lowest
    eigenvector and the shifted solve is short, p adds that eigenvector to reach the boundary."""
    w, V = torch.linalg.eigh((h + h.T) / 2)
    a = V.T @ g

    def solve(lam):
        return -V @ (a / (w + lam))

    if w[0] > 0:
        p = solve(0.0)
        if p.norm() <= radius:
            return p, float(-(g @ p + p @ h @ p / 2))
    low = max(0.0, -float(w[0]))
    bottom = w <= w[0] + 1e-12 * w.abs().max()  # the lowest eigenspace
    if bool((a[bottom].abs() <= 1e-14 * max(float(g.norm()), 1e-300)).all()):
        inner = -V[:, ~bottom] @ (a[~bottom] / (w[~bottom] + low))
        if inner.norm() <= radius:  # the hard case: along the bottom eigenvector to the boundary
            v = V[:, 0] * (-1.0 if float(g @ V[:, 0]) > 0 else 1.0)
            p = inner + math.sqrt(max(radius**2 - float(inner @ inner), 0.0)) * v
            return p, float(-(g @ p + p @ h @ p / 2))
    lo, hi = low, low + float(g.norm()) / radius  # |p(hi)| <= |g| / (hi - low) = radius
    for _ in range(BISECTIONS):
        mid = (lo + hi) / 2
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if solve(mid).norm() > radius else (lo, mid)
    p = solve(hi)
    return p, float(-(g @ p + p @ h @ p / 2))


def polish(evaluate, hessian_fn, z, u, g, h, max_steps):
    """Trust-region Newton from z (potential u, gradient g, Hessian h) for at most ``max_steps``
    trial points; ``evaluate(z)`` gives (potential, gradient), or (inf, None) where the model
    refuses z (a rejected trial: the radius shrinks). A trial is accepted when it achieves ETA of
    the predicted decrease, or, where that decrease is below the potential's rounding, when it
    lowers both the potential and |grad| (a Newton step at a mode to rounding), and the polish ends
    after such a step. Returns (z, u, g, h, trial evaluations)."""
    radius, evaluations = None, 0
    for _ in range(max_steps):
        if radius is None:  # the Newton step's length at a positive definite Hessian, else 1
            w, V = torch.linalg.eigh((h + h.T) / 2)
            radius = float((V.T @ g / w).norm()) if w[0] > 0 else 1.0
        p, predicted = step(g, h, radius)
        if not predicted > 0:  # a stationary point of the model with no descent: nothing to gain
            break
        u_new, g_new = evaluate(z + p)
        evaluations += 1
        ratio = (u - u_new) / predicted if g_new is not None else -math.inf
        rounding = predicted <= 1e-13 * max(1.0, abs(u))
        if ratio < 0.25:
            radius = 0.25 * float(p.norm())
        elif ratio > 0.75 and float(p.norm()) > 0.99 * radius:
            radius *= 2
        if ratio > ETA or (g_new is not None and u_new <= u and g_new.norm() < g.norm()):
            z, u, g = z + p, u_new, g_new
            h = hessian_fn(z)
        if rounding:  # a step below the potential's rounding was the last that could tell
            break
    return z, u, g, h, evaluations
