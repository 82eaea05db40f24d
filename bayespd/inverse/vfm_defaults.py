"""The PD-VFM with defaults fit for measured data.

Default (``work="local"``): the local virtual work of ``vfm_local`` (the weak form on the
measured grid, no PD surface effect) with the fields of ``local_fields`` (a harmonic load field
and bilinear hats kept off supports, loads and holes). The moduli do not depend on m or the
ramp; ``extra["m"]`` and ``extra["rule"]`` are None. Measured on scikit-fem fields: K and G
within 0.25 % (beam) and 0.06 % (plate with a hole), where the PD work below gave +1 to +5 %,
with 3-13x smaller standard errors at 1 % noise (docs/results.md, VFM).

``work="pd"``: the PD virtual work (``vfm.VirtualWork``) with interior fields, and the horizon
m = delta / h and partial-volume ramp chosen by the residual at the estimate (no truth needed):

Fields (:func:`interior_fields`): one *load field* u*_0 = s(x) d, d the unit direction of the
total load and s = d_D / (d_D + d_L) (d_D, d_L: distances to the nearest constrained and
loaded particle), 0 on every constrained particle and 1 on the loaded ones, so that
W*_ext = |F| and it alone fixes the scale; and C1 *bumps* (``virtual_fields.bump``), each
kept only where its support, widened by ``clearance``, lies inside the body and holds no
constrained or loaded particle: they see no free surface (no PD surface effect), W*_ext = 0,
and constrain the ratio of the moduli (Delorme 2018 eq 25 with many fields).

Selection (:func:`estimate`): for every candidate (m, rule), the closed form
(``vfm.identify``) gives a = argmin_a sum_k r_k(a)^2 and the residual

    Phi(m, rule) = sqrt(sum_k r_k(a*)^2 / sum_k (W*_ext,k)^2)      (Delorme 2018 eq 25)

at that estimate; we take the (m, rule) of least Phi. The fields are the same functions for
every candidate (the clearance is that of the largest horizon) and so is W*_ext: Phi then
compares how nearly each discrete operator admits the measured field as an equilibrium of
*some* isotropic (K, G), i.e. the model error of the operator, not the noise. It needs more
fields than the two unknowns: with two, Phi = 0 for every candidate and nothing is chosen.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from scipy.spatial import cKDTree

import bayespd as bp
from bayespd.inverse import virtual_fields as vf
from bayespd.inverse.local_fields import local_fields
from bayespd.inverse.vfm import VFMResult, VirtualWork, identify, measured
from bayespd.inverse.vfm_local import LocalWork
from bayespd.inverse.vfm_noise import MAX_SE, warn_if_noisy, weighted_identify
from bayespd.validate import count, positive

MS = (2, 3, 4, 5)
# (margin, size) / h tried when the default fields are too few: hats 3 h apart keep a margin of 3 h
# (then 2 h). Measured on the FE plate with a hole at h = 1 mm, nu 0.15-0.45, noise-free: K, G
# within 0.11 % (3, 3) and 0.18 % (2, 3); fewer fields (margin 4 h, hats 3 h: 9 fields; 3 h, 6 h:
# 5) gave 1.7-2.3 % (docs/results.md, VFM).
FALLBACK = ((3, 3), (2, 3))
RULES = ("linear", "smooth")


class FallbackFieldsWarning(UserWarning):
    """The default local fields were too few on this grid; smaller ones were used."""


def load_field(scene):
    """u*_0 = s(x) d of the module docstring, as a callable."""
    p = scene.particles
    fixed = scene.constraints.fixed_particles
    loaded = np.abs(scene.force.numpy()).sum(1) > 0
    total = scene.force.numpy().sum(0)
    if not fixed.any() or not loaded.any() or not np.any(total):
        raise ValueError("the default VFM fields need a scene with Dirichlet particles and a "
                         "non-zero total load: pass fields= for displacement-controlled scenes")
    d = total / np.linalg.norm(total)
    to_fixed, to_loaded = cKDTree(p.x[fixed]), cKDTree(p.x[loaded])

    def u(x):
        dD, dL = to_fixed.query(x)[0], to_loaded.query(x)[0]
        return (dD / np.maximum(dD + dL, 1e-300))[:, None] * d[None, :]

    return u


def interior_fields(scene, clearance: float, size: float | None = None):
    """[load field] + the bumps of a regular cell grid over the bounding box that keep
    ``clearance`` from every free surface, hole, constrained and loaded particle; ``size``:
    the cells' target width (default: the smaller extent of the box less the clearance)."""
    p = scene.particles
    x, h = p.x, p.h
    lo, hi = x.min(0) + clearance, x.max(0) - clearance
    if np.any(hi <= lo):
        raise ValueError(f"clearance {clearance:g} leaves no interior: the body is too thin for "
                         "interior fields at this horizon; pass fields= or smaller ms=")
    size = (hi - lo).min() if size is None else positive("size", size, "give the bump cells' width")
    counts = np.maximum(np.round((hi - lo) / size).astype(int), 1)
    radius = (hi - lo) / counts / 2
    body = cKDTree(x)
    busy = cKDTree(x[scene.constraints.fixed_particles | (np.abs(scene.force.numpy()).sum(1) > 0)])
    fields = [load_field(scene)]
    for idx in np.ndindex(*counts):
        centre = lo + radius * (2 * np.asarray(idx) + 1)
        a, b = centre - radius - clearance, centre + radius + clearance
        grid = np.stack(np.meshgrid(*[np.arange(a[k], b[k] + h / 2, h / 2) for k in range(p.dim)]), -1)
        grid = grid.reshape(-1, p.dim)
        if body.query(grid)[0].max() > 0.75 * h * np.sqrt(p.dim):  # a hole or an edge inside
            continue
        if busy.query(grid)[0].min() <= h:
            continue
        fields += [vf.bump(centre, radius, c) for c in range(p.dim)]
    return fields


def with_rule(scene, rule: str, delta_max: float):
    """The scene rebuilt with bonds of ``rule`` found at ``delta_max`` (same law, constraints,
    loads and observation)."""
    m = scene.material
    material = type(m)(m.particles, bp.find_bonds(m.particles, delta_max, rule), plane=m.plane,
                       influence=m.influence, surface_correction=m.surface_correction)
    return bp.Scene(material, scene.dirichlet, scene.loads, scene.observation)


def model_spread(candidates, best, dof: int) -> dict:
    """The largest relative change of K and G from ``best`` over the candidates the noise cannot
    tell from it: chi2 within 2 sd of a chi2 with ``dof`` degrees of freedom (2 sqrt(2 dof)) of
    the least. A model-form uncertainty that the standard error does not contain."""
    close = [c for c in candidates if c["score"] <= best["score"] + 2 * np.sqrt(2 * max(dof, 1))]
    return {k: max(abs(c[k] / best[k] - 1) for c in close) for k in ("K", "G")}


def estimate(scene, u, *, observed=None, sigma: float | None = None, fields=None, work: str = "local",
             ms=MS, rules=RULES, size: float | None = None, clearance: float | None = None,
             margin: float | None = None, max_se: float | None = MAX_SE) -> VFMResult:
    """K, G of the LPS ``scene`` from the measured field ``u`` (N, dim; NaN where not
    measured) by the closed-form VFM (module docstring).

    ``work="local"`` (default): the local virtual work (``vfm_local.LocalWork``, particles on
    a grid) with ``fields`` defaulting to ``local_fields.local_fields(scene, margin, size)``
    (margin 4 h, hats 8 h apart, 4 h when ``sigma`` is given: half the standard errors, at
    1 % noise K 5 % and G 1.1 % on the plate with a hole, for a noise-free error 0.4 % in place
    of 0.1 %); ``ms``, ``rules`` and ``clearance`` are not used.
    ``work="pd"``: the PD virtual work at the (m, rule) of least residual; ``fields`` default
    to :func:`interior_fields` with ``clearance`` (default 2 max(ms) h + h: no PD surface
    effect under the bumps) and bump cells of width ``size``.

    ``sigma``: the noise sd of each measured displacement. Given, every candidate is solved
    by ``vfm_noise.weighted_identify`` (noise-optimal combination of the fields, errors in
    variables corrected), the residual criterion is its chi2 (Phi weighted by the noise
    covariance), and the result's ``extra['se']`` holds the relative standard errors of K and
    G, and ``extra['model_spread']`` (:func:`model_spread`) how far the candidates the noise
    cannot tell apart differ; a :class:`vfm_noise.NoisyEstimateWarning` says when either
    exceeds ``max_se``. Candidates whose system the noise swamps are skipped
    (``extra['candidates']`` says why).

    The result's ``extra`` holds the chosen ``m``, ``rule``, ``delta`` and every candidate's
    ``phi`` (and ``chi2``, ``se``) and estimates."""
    if work == "local":
        return _local_estimate(scene, u, observed, sigma, fields, size, margin, max_se)
    if work != "pd":
        raise ValueError(f"work must be 'local' (the weak form on the grid) or 'pd' (the PD virtual work), got {work!r}")
    ms = tuple(count("ms entry", m, 1, "m = delta / h is at least 1") for m in ms)
    if not ms or not rules or set(rules) - set(RULES):
        raise ValueError(f"ms must be a non-empty tuple of integers and rules a subset of {RULES}")
    h = scene.particles.h
    if fields is None:
        clear = 2 * max(ms) * h + h if clearance is None else positive("clearance", clearance, "give a distance")
        fields = interior_fields(scene, clear, size)
    _refuse_exactly_determined(fields)
    candidates, failures = [], []
    for rule in rules:
        sc = with_rule(scene, rule, max(ms) * h)
        for m in ms:
            work = VirtualWork(sc, fields, {"delta": m * h})
            if sigma is None:
                res = identify(work, u, observed=observed)
                score = res.phi
            else:
                try:
                    res = weighted_identify(work, u, sigma, observed=observed, max_se=None)
                except ValueError as err:
                    failures.append({"m": m, "rule": rule, "error": str(err)})
                    continue
                score = res.extra["chi2"]
            candidates.append({"m": m, "rule": rule, "phi": res.phi, "score": score, "K": res.params["K"],
                               "G": res.params["G"], "se": res.extra.get("se"), "result": res})
    if not candidates:
        raise ValueError(f"no candidate (m, rule) gave positive moduli: {failures[-1]['error']}")
    best = min(candidates, key=lambda c: c["score"])
    table = [{k: v for k, v in c.items() if k != "result"} for c in candidates] + failures
    extra = dict(best["result"].extra, m=best["m"], rule=best["rule"], delta=best["m"] * h,
                 candidates=table, fields=len(fields))
    if sigma is not None:
        extra["model_spread"] = model_spread(candidates, best, extra["dof"])
        if max_se is not None:
            warn_if_noisy(extra["se"], sigma, max_se, extra["model_spread"])
    how = "least residual" if sigma is None else "least chi2, noise-weighted"
    return dataclasses.replace(best["result"], method=f"{best['result'].method}, (m, rule) by {how}",
                               extra=extra)


def _refuse_exactly_determined(fields):
    if len(fields) <= 2:
        raise ValueError(f"{len(fields)} virtual fields: the system for (K, G) is exactly determined, "
                         "Phi = 0 whatever the model error and the residual cannot choose or check; give at "
                         "least three fields (or a smaller size= or margin= for more bumps or hats)")


def _default_local_fields(scene, u, observed, sigma, size, margin) -> list:
    """``local_fields`` at ``margin`` and ``size`` (defaults 4 h and 8 h; 4 h with noise: hats 4 h
    apart bring the weighting nearer the noise-optimal fields). When neither is given and the
    defaults leave fewer than three fields (a coarse grid: on the plate with a hole at h = 1 mm
    every hat meets the hole, the clamp or the load), the first of FALLBACK (margin, size) / h
    that leaves three, with a :class:`FallbackFieldsWarning`."""
    h = scene.particles.h
    unmeasured = ~measured(scene.particles.x, u, observed)[1].all(1)
    unmeasured = unmeasured if unmeasured.any() else None
    given = margin is not None or size is not None
    try:
        fields = local_fields(scene, margin, size if size is not None or sigma is None else 4 * h, unmeasured)
    except ValueError:
        if given:
            raise
        fields = []
    if given or len(fields) > 2:
        return fields
    for m, s in FALLBACK:
        try:
            fallback = local_fields(scene, m * h, s * h, unmeasured)
        except ValueError:
            continue
        if len(fallback) > 2:
            warnings.warn(f"the default virtual fields (margin 4 h, hats {4 if sigma else 8} h apart) leave "
                          f"{len(fields)} field(s) on this grid (h = {h:g}): using margin {m:g} h and hats {s:g} h "
                          "apart. Pass margin= and size= to choose", FallbackFieldsWarning, stacklevel=4)
            return fallback
    return fields


def _local_estimate(scene, u, observed, sigma, fields, size, margin, max_se) -> VFMResult:
    """``estimate(work="local")``: one closed form (or noise-weighted closed form) on the local work."""
    if fields is None:
        fields = _default_local_fields(scene, u, observed, sigma, size, margin)
    _refuse_exactly_determined(fields)
    work = LocalWork(scene, fields, {"delta": scene.material.bonds.delta_max})
    if sigma is None:
        res = identify(work, u, observed=observed)
    else:
        res = weighted_identify(work, u, sigma, observed=observed, max_se=None)
    extra = dict(res.extra, m=None, rule=None, delta=None, fields=len(fields), work="local")
    if sigma is not None:
        extra["model_spread"] = {"K": 0.0, "G": 0.0}
        if max_se is not None:
            warn_if_noisy(extra["se"], sigma, max_se)
    return dataclasses.replace(res, method=f"{res.method}, local virtual work", extra=extra)
