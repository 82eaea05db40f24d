"""The MD sheet's measured static dispersion: its compliance C(k) (2 x 2) at the wavevectors of the
sinusoidal loads (paper 004 eq 5.1), and a PD symbol's relative error against it (issue 28).

A linear, translation-invariant sheet answers a load at wavevector k with y_hat(k) = C(k) f_hat(k)
(PD: C = S(k)^-1, ``PeriodicSheet.symbol``). A load cos(k1 x1) cos(k2 x2) e_a excites the modes
(+-k1, +-k2); the loads a = x and a = y at one (n1, n2) give C's columns at (k1, k2), and at the
mirror mode (k1, -k2) they give M C M (M = diag(1, -1): the grid and the honeycomb are mirror
symmetric about both axes), which is averaged in. The PD-MD misfit is then one symmetric relative
compliance error per orbit {(+-k1, +-k2)},

    Delta = L^T C L - I,   S = L L^T   (0 when C = S^-1),

its off-diagonal entry only where n1 n2 != 0 (on the axes both vanish by the mirror symmetry).
These are the independent errors the data hold: a nodal likelihood counts each orbit's 2 N values
of each load. An offset common to every orbit (models/md_dispersion.py's tau) is tied by them to the
parameters: predictive error fields draw it from its conditional posterior (``common_offset_posterior``).
With a measurement error of the compliances (models/md_dispersion.py's sigma_m, which
``off_orbit_response`` measures on single-wave records) the training orbits' model errors are known
given the parameters only up to it (``orbit_error_posterior``); ``wave_power_share`` says how much of
a load lies on given orbits. A predicted record's error field (``error_field``) keeps the mirror
symmetry (one error per orbit, M Delta M at the mirror pair, diagonal on the axes), and
``unheld_response`` adds the response no compliance holds as a white floor.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from bayespd.linalg.sparse import NotPositiveDefiniteError


def measured_compliance(forces: torch.Tensor, y: torch.Tensor, n: int) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """(modes (O, 2): the lattice indices (n1, n2 >= 0) of each orbit, C (O, 2, 2), off_diagonal (O,):
    n1 n2 != 0) from sinusoidal loads ``forces`` and zero-mean responses ``y`` (loads, n * n, 2),
    nodes x-major; each (n1, n2) needs its x and its y load."""
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2))
    y_hat = torch.fft.fft2(torch.as_tensor(y).reshape(-1, n, n, 2), dim=(1, 2))
    quadrant = f_hat[:, : n // 2 + 1, : n // 2 + 1].abs().pow(2)
    columns = {}
    for m in range(len(f_hat)):
        n1, n2, a = np.unravel_index(int(quadrant[m].argmax()), quadrant[m].shape)
        if (n1, n2) == (0, 0):
            raise ValueError(f"load {m} has no wave: measured_compliance needs the sinusoidal loads of eq 5.1")
        both = [(n1, n2), (n1, -n2 % n)] if n1 and n2 else [(n1, n2)]
        column = [(y_hat[m, i, j] / f_hat[m, i, j, a]).real for i, j in both]
        if len(column) == 2:  # the mirror mode's column of M C M, mapped back
            mirror = torch.tensor([1.0, -1.0], dtype=column[1].dtype)
            column = [(column[0] + mirror * mirror[a] * column[1]) / 2]
        columns.setdefault((int(n1), int(n2)), {})[int(a)] = column[0]
    missing = sorted(k for k, v in columns.items() if len(v) != 2)
    if missing:
        raise ValueError(f"the waves {missing} lack their x or y load: each (n1, n2) needs both (eq 5.1's set)")
    modes = np.array(sorted(columns))
    C = torch.stack([torch.stack([columns[tuple(k)][0], columns[tuple(k)][1]], -1) for k in modes])
    C = (C + C.transpose(-1, -2)) / 2  # a static compliance is symmetric (Maxwell-Betti)
    return modes, C, torch.as_tensor((modes[:, 0] > 0) & (modes[:, 1] > 0))


def _orbit_index(modes, n: int) -> torch.Tensor:
    """Flat indices (into an n x n FFT grid) of every lattice wavevector of the orbits
    {(+-n1, +-n2)} of ``modes`` (O, 2)."""
    found = {(s1 * n1 % n) * n + (s2 * n2 % n) for n1, n2 in np.asarray(modes).tolist() for s1 in (1, -1)
             for s2 in (1, -1)}
    return torch.as_tensor(sorted(found))


def wave_power_share(forces: torch.Tensor, modes, n: int) -> torch.Tensor:
    """The fraction (loads,) of each load's power (|f_hat|^2 summed over both components and every
    k != 0) on the lattice wavevectors of the orbits ``modes`` (O, 2) (e.g. the training orbits of
    ``measured_compliance``); ``forces`` (loads, n * n, 2), nodes x-major."""
    power = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2)).abs().pow(2).sum(-1)
    power = power.reshape(len(power), -1)
    power[:, 0] = 0.0
    return power[:, _orbit_index(modes, n)].sum(1) / power.sum(1)


def off_orbit_response(forces: torch.Tensor, y: torch.Tensor, n: int) -> torch.Tensor:
    """For single-wave loads (eq 5.1): the relative norm (loads,) of each zero-mean response ``y``
    outside its load's orbit (the (n1, n2) of the load's strongest coefficient). A linear,
    translation-invariant sheet answers on the orbit alone (0); the rest is the response no
    compliance holds: the harmonics of the MD sheet's non-linearity (k1 + k2 of the load's own
    waves, e.g. 2 k) and the coarse graining's leakage."""
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2))
    y_power = torch.fft.fft2(torch.as_tensor(y).reshape(-1, n, n, 2), dim=(1, 2)).abs().pow(2).sum(-1)
    out = []
    for m in range(len(f_hat)):
        n1, n2 = np.unravel_index(int(f_hat[m].abs().pow(2).sum(-1).argmax()), (n, n))
        power = y_power[m].reshape(-1).clone()
        total = power.sum()
        power[_orbit_index([(n1, n2)], n)] = 0.0
        out.append((power.sum() / total).sqrt())
    return torch.stack(out)


def unheld_part(forces: torch.Tensor, y: torch.Tensor, n: int) -> torch.Tensor:
    """The relative norm (loads,) of each zero-mean sinusoidal record ``y`` (eq 5.1's ``forces``,
    (loads, n * n, 2)) beyond the response of the compliance measured from the records themselves
    (``measured_compliance``, put on each orbit's wavevectors by ``orbit_errors_on_lattice``): the
    off-orbit response (``off_orbit_response``) plus the on-orbit part that no real, symmetric,
    mirror-symmetric compliance holds (a phase shift of the wave, the Maxwell-Betti and mirror
    asymmetries). 0 for a linear, translation- and mirror-invariant sheet."""
    modes, C, _ = measured_compliance(forces, y, n)
    index, C_lattice = orbit_errors_on_lattice(modes, C, n)
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2)).reshape(len(forces), -1, 2)
    held = torch.zeros_like(f_hat)
    held[:, index + 1] = torch.einsum("kab,mkb->mka", C_lattice.to(f_hat.dtype), f_hat[:, index + 1])
    held = torch.fft.ifft2(held.reshape(-1, n, n, 2), dim=(1, 2)).real.reshape(y.shape)
    return (y - held).norm(dim=(1, 2)) / y.norm(dim=(1, 2))


def shell_power_share(forces: torch.Tensor, shell: torch.Tensor, n: int, shells: int) -> torch.Tensor:
    """The fraction (loads, shells) of each load's power (|f_hat|^2, both components, k != 0) on each
    shell of |k| h; ``shell`` (n * n - 1,): the shell of each of ``PeriodicSheet.wavevectors``
    (``shell_of``), ``forces`` (loads, n * n, 2), nodes x-major."""
    power = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2)).abs().pow(2).sum(-1)
    power = power.reshape(len(power), -1)[:, 1:]
    share = torch.zeros(len(power), shells, dtype=power.dtype).index_add(1, torch.as_tensor(shell), power)
    return share / share.sum(1, keepdim=True)


def unheld_response_sd(forces: torch.Tensor, y: torch.Tensor, loads: torch.Tensor, shell: torch.Tensor, n: int,
                       shells: int) -> torch.Tensor:
    """The unheld response's sd (loads,) for the records of ``loads`` (m, n * n, 2), from the training
    records' ``unheld_part`` r_t (sinusoidal ``forces`` and zero-mean responses ``y``, (T, n * n, 2)),
    which grows with |k| h (on the MD sheet 0.16 % on |k| h < 0.5, 0.74 % beyond 1.5): per shell b of |k| h (``shell`` as
    ``shell_power_share``) the training loads' power-weighted mean square s_b^2 = sum_t P_tb r_t^2 /
    sum_t P_tb, then sd_m^2 = sum_b P_mb s_b^2 with P the shell power shares; a shell no training
    load reaches is refused."""
    r = unheld_part(forces, y, n)
    train = shell_power_share(forces, shell, n, shells)
    weight = train.sum(0)
    share = shell_power_share(loads, shell, n, shells)
    empty = (weight < 1e-9 * weight.sum()) & (share.max(0).values > 1e-9)  # 1e-9: above the FFT's rounding
    if bool(empty.any()):
        raise ValueError(f"no training load reaches the shells {empty.nonzero().flatten().tolist()} of |k| h that the "
                         f"loads excite: add training waves there or merge the shells")
    return (share @ ((train.T @ r.pow(2)) / weight.clamp(min=1e-300))).sqrt()  # a rounding-empty shell: share ~ 0


def unheld_response(records: torch.Tensor, sd, generator: torch.Generator) -> torch.Tensor:
    """``records`` (loads, N, 2) plus the response no compliance holds (``unheld_part``: the sheet's
    harmonics, the coarse graining's leakage, the waves' phase shifts), drawn white: N(0, (sd_m r_m)^2) at every
    node and component, r_m the rms of record m over its nodes and components, ``sd`` a number or
    (loads,) (``unheld_response_sd``). White noise puts a share 4 / N of its power on one orbit, so
    the draw's unheld part is sd (1 - O(1 / N)): the training records' ``unheld_part`` is the sd
    that reproduces their own. It gives the band a floor where a relative compliance
    error gives none (a load's zero crossings, the cross component of an axis wave)."""
    records = torch.as_tensor(records)
    sd = torch.as_tensor(sd, dtype=records.dtype).expand(len(records))
    if not bool((sd >= 0).all()):
        raise ValueError(f"the unheld response's sd must be non-negative (a relative size), got {sd.tolist()}")
    scale = records.pow(2).mean((-2, -1)).sqrt() * sd
    return records + scale[:, None, None] * torch.randn(records.shape, dtype=records.dtype, generator=generator)


def relative_compliance_error(S: torch.Tensor, C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(Delta = L^T C L - I (O, 2, 2), log det S (O,)) for symbols S (O, 2, 2), S = L L^T; a symbol
    that is not positive definite (an operator that is not solvable) raises NotPositiveDefiniteError."""
    L, info = torch.linalg.cholesky_ex(S)
    if bool((info > 0).any()):
        raise NotPositiveDefiniteError("the PD symbol is not positive definite at a measured wavevector: the "
                                       "kernel violates the solvability constraint (eq 4.4)")
    return L.transpose(-1, -2) @ C @ L - torch.eye(2, dtype=S.dtype), torch.logdet(S)


def shell_of(wavevectors, h: float, edges) -> torch.Tensor:
    """The shell (0 .. len(edges)) of each wavevector (..., 2) by |k| h against ``edges`` (positive,
    increasing)."""
    edges = np.asarray(edges, float)
    if edges.ndim != 1 or not np.all(np.diff(edges) > 0) or not np.all(edges > 0):
        raise ValueError(f"shell edges must be positive and increasing in |k| h, got {edges}")
    return torch.as_tensor(np.searchsorted(edges, np.linalg.norm(np.asarray(wavevectors), axis=-1) * h))


class SymmetricNormal(NamedTuple):
    """A normal law of symmetric 2 x 2 matrices (the common offset c, or a batch (..., 2, 2) of
    orbit errors): entries 00, 11, 01 independent, with means ``mean`` and sds ``sd`` (both
    (..., 2, 2), symmetric)."""

    mean: torch.Tensor
    sd: torch.Tensor

    def sample(self, generator: torch.Generator) -> torch.Tensor:
        z = torch.randn(*self.mean.shape[:-2], 3, dtype=self.mean.dtype, generator=generator)
        return self.mean + self.sd * _symmetric(z.unbind(-1))


_ENTRY_SCALE = (1.0, 1.0, math.sqrt(0.5))  # entries 00, 11, 01: sd s and tau on the diagonal, s / sqrt 2 and tau / sqrt 2 off it


def _symmetric(values) -> torch.Tensor:
    a, b, c = values
    return torch.stack([torch.stack([a, c], -1), torch.stack([c, b], -1)], -2)


def common_offset_prior(tau: float) -> SymmetricNormal:
    """The offset's prior of models/md_dispersion.py: mean 0, sd tau on the diagonal and tau / sqrt 2
    off it (the law of CompliancePerOrbit's common part)."""
    if not tau > 0:
        raise ValueError(f"tau must be positive, got {tau}")
    tau = torch.as_tensor(tau, dtype=torch.float64)
    return SymmetricNormal(torch.zeros(2, 2, dtype=tau.dtype), _symmetric([tau * w for w in _ENTRY_SCALE]))


def common_offset_posterior(Delta: torch.Tensor, s: torch.Tensor, tau: float, off_diagonal) -> SymmetricNormal:
    """The offset's conditional posterior given the relative errors ``Delta`` (O, 2, 2) of the
    training orbits at fixed parameters (``relative_compliance_error``), their sds ``s`` (O,) and
    tau; ``off_diagonal`` (O,): the orbits with an 01 entry (n1 n2 != 0).

    CompliancePerOrbit's law, entry e in (00, 11, 01) with scale w_e = (1, 1, 1 / sqrt 2):
    Delta_oe = c_e + eps_oe, c_e ~ N(0, w_e^2 tau^2), eps_oe ~ N(0, w_e^2 s_o^2) independent over
    the orbits O_e holding the entry (all for 00 and 11, the off-diagonal ones for 01). Conjugate:
    c_e | Delta ~ N(m_e, v_e) with v_e = w_e^2 / (1 / tau^2 + sum_{O_e} 1 / s_o^2) and
    m_e = (v_e / w_e^2) sum_{O_e} Delta_oe / s_o^2 (w_e cancels from the mean; the prior where O_e
    is empty)."""
    Delta, s = torch.as_tensor(Delta), torch.as_tensor(s, dtype=torch.float64)
    off = torch.as_tensor(off_diagonal, dtype=torch.bool)
    if Delta.ndim != 3 or Delta.shape[1:] != (2, 2) or s.shape != Delta.shape[:1] or off.shape != s.shape:
        raise ValueError(f"Delta must be (O, 2, 2) with s and off_diagonal (O,), got {tuple(Delta.shape)}, "
                         f"{tuple(s.shape)}, {tuple(off.shape)}")
    if not (bool((s > 0).all()) and tau > 0):
        raise ValueError(f"the error sds must be positive, got s = {s.tolist()}, tau = {tau}")
    precision = 1.0 / s**2
    mean, sd = [], []
    for value, held, w in ((Delta[:, 0, 0], torch.ones_like(off), _ENTRY_SCALE[0]),
                           (Delta[:, 1, 1], torch.ones_like(off), _ENTRY_SCALE[1]),
                           (Delta[:, 0, 1], off, _ENTRY_SCALE[2])):
        total = 1.0 / tau**2 + precision[held].sum()
        mean.append((precision[held] * value[held]).sum() / total)
        sd.append(w * total.rsqrt())
    return SymmetricNormal(_symmetric(mean), _symmetric(sd))


def orbit_error_posterior(Delta: torch.Tensor, s: torch.Tensor, measurement: float, offset: torch.Tensor) -> SymmetricNormal:
    """The law of the training orbits' model errors c + eps_o given their measured relative errors
    ``Delta`` (O, 2, 2) = c + eps_o + m_o, the common offset c = ``offset`` (2, 2; a draw of
    ``common_offset_posterior`` with the orbits' total sds sqrt(s^2 + measurement^2)), the model
    errors' sds ``s`` (O,) and the measurement error's sd ``measurement`` (models/md_dispersion.py):
    per entry e, eps_oe ~ N(0, w_e^2 s_o^2) and m_oe ~ N(0, w_e^2 sigma^2) give, with
    r_o = s_o^2 / (s_o^2 + sigma^2), mean c + r_o (Delta_o - c) and sd w_e sqrt(r_o) sigma
    (sigma = 0: Delta itself, the measured compliance taken as exact)."""
    Delta, s = torch.as_tensor(Delta), torch.as_tensor(s, dtype=torch.float64)
    if Delta.ndim != 3 or Delta.shape[1:] != (2, 2) or s.shape != Delta.shape[:1]:
        raise ValueError(f"Delta must be (O, 2, 2) with s (O,), got {tuple(Delta.shape)}, {tuple(s.shape)}")
    if not (bool((s > 0).all()) and measurement >= 0):
        raise ValueError(f"the error sds must be positive (measurement: non-negative), got s = {s.tolist()}, "
                         f"measurement = {measurement}")
    r = (s**2 / (s**2 + measurement**2))[:, None, None]
    scale = _symmetric([torch.as_tensor(w, dtype=s.dtype) for w in _ENTRY_SCALE])
    return SymmetricNormal(offset + r * (Delta - offset), scale * (r.sqrt() * measurement).expand(Delta.shape))


def orbit_errors_on_lattice(modes, Delta: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(index (m,) into ``PeriodicSheet.wavevectors``, Delta (m, 2, 2)): every lattice wavevector of
    the orbits {(+-n1, +-n2)} of ``modes`` (O, 2) with its relative error as measured_compliance
    defines it: Delta_o at (n1, n2) and (-n1, -n2), M Delta_o M at the mirror pair (M = diag(1, -1));
    where two of those coincide (an axis, the Nyquist index) their mean (on an axis Delta_o's
    diagonal: the off-diagonal entry is not data there)."""
    Delta = torch.as_tensor(Delta)
    M = torch.tensor([1.0, -1.0], dtype=Delta.dtype)
    found = {}
    for (n1, n2), D in zip(np.asarray(modes).tolist(), Delta):
        mirrored = M[:, None] * D * M[None, :]
        for i, j, value in ((n1, n2, D), (-n1 % n, -n2 % n, D), (n1, -n2 % n, mirrored), (-n1 % n, n2, mirrored)):
            found.setdefault(i * n + j - 1, []).append(value)
    index = sorted(found)
    return torch.as_tensor(index), torch.stack([torch.stack(found[k]).mean(0) for k in index])


def mirror_frame(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(rep, sign) (n * n - 1,) for ``PeriodicSheet.wavevectors`` on the n x n lattice: the flat
    index of each wavevector's orbit representative (min(n1, n - n1), min(n2, n - n2)) (the frame of
    ``measured_compliance``'s Delta_o) and the sign s1 s2 of its 01 entry in that frame (s_i = +1 for
    0 < n_i < n / 2, -1 beyond): the mirror symmetry maps Delta_o to M Delta_o M at the mirror pair.
    sign = 0 on the self-mirror wavevectors, an axis or a Nyquist line (n / 2, n even), which a
    mirror maps onto themselves (or -k): there M Delta M = Delta, so Delta_01 = 0."""
    index = np.arange(n)
    fold = np.minimum(index, n - index)
    side = np.where((index == 0) | (2 * index == n), 0, np.where(2 * index < n, 1, -1))
    rep = (fold[:, None] * n + fold[None, :]).ravel()[1:]
    return torch.as_tensor(rep), torch.as_tensor((side[:, None] * side[None, :]).ravel()[1:])


def _in_frame(Delta: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """Orbit-frame matrices (m, 2, 2) mapped to their wavevectors: the 01 entry times ``sign`` (m,)."""
    scale = torch.ones_like(Delta)
    scale[:, 0, 1] = scale[:, 1, 0] = sign.to(Delta.dtype)
    return Delta * scale


def error_field(S: torch.Tensor, forces: torch.Tensor, s: torch.Tensor, offset: torch.Tensor, n: int,
                generator: torch.Generator, known: tuple[torch.Tensor, torch.Tensor] | None = None,
                measurement: float = 0.0) -> torch.Tensor:
    """One draw of the model error u_md - u_pd (loads, n * n, 2) under ``forces`` (loads, n * n, 2):
    at each k != 0, L^-T Delta(k) L^-1 f_hat(k) with S (n * n - 1, 2, 2) the symbols at
    ``PeriodicSheet.wavevectors``. Delta is drawn once per orbit {(+-k1, +-k2)} in its
    representative's frame (``mirror_frame``): symmetric, entries N(0, s_k^2) (s_k^2 / 2 off the
    diagonal; ``s`` (n * n - 1,), a function of |k|) plus ``offset`` (2, 2, symmetric), common to every
    orbit (a draw of ``common_offset_prior`` or ``common_offset_posterior``), and mapped to the
    orbit's wavevectors as the mirror symmetry demands (M Delta M at the mirror pair, so Delta(-k) =
    Delta(k), and Delta_01 = 0 on the self-mirror axes and Nyquist lines, where the sheet's compliance
    and the PD symbol are both diagonal); ``known``: (index, Delta) of wavevectors whose error the
    data fix (``orbit_errors_on_lattice``), which replace the draw there; ``measurement``: the sd of
    the predicted record's own measurement error, a fresh error of the same law (per orbit,
    mirrored) at every k (models/md_dispersion.py)."""
    if offset.shape != (2, 2) or not torch.equal(offset, offset.T):
        raise ValueError(f"the common offset must be a symmetric 2 x 2 matrix (SymmetricNormal.sample), got {offset}")
    rep, sign = mirror_frame(n)

    def symmetric_draw(sd):  # one N(0, sd^2) (N(0, sd^2 / 2) off the diagonal) matrix per orbit
        A = sd * torch.randn(n * n, 2, 2, dtype=S.dtype, generator=generator)[rep]
        return (A + A.transpose(-1, -2)) / 2

    Delta = _in_frame(symmetric_draw(s[:, None, None]) + offset, sign)
    if known is not None:
        Delta[known[0]] = known[1].to(Delta.dtype)
    if measurement > 0:
        Delta = Delta + _in_frame(symmetric_draw(measurement), sign)
    Linv = torch.linalg.inv(torch.linalg.cholesky(S)).to(torch.complex128)
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2)).reshape(len(forces), -1, 2)
    e_hat = torch.zeros_like(f_hat)
    e_hat[:, 1:] = torch.einsum("kba,kbc,kcd,mkd->mka", Linv, Delta.to(Linv.dtype), Linv, f_hat[:, 1:])
    return torch.fft.ifft2(e_hat.reshape(-1, n, n, 2), dim=(1, 2)).real.reshape(forces.shape)
