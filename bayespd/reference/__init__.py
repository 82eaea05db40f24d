"""Reference solutions to verify the PD models against.

``fem``: scikit-fem linear elasticity on boxes (or any quad/hex mesh) with volume supports and
body loads (scikit-fem is imported only when solving; ``pip install scikit-fem``).
``three_point_bending`` (seed 001's beam, 2D plane stress), ``plate_with_hole`` (the demo's
plate in tension, 2D plane stress) and ``cantilever`` (3D): the PD scene and its FE peer.
``lattice``: the effective tensor C_m of an LPS grid at fixed m. ``compare``: relative L2
errors at the particles and observed orders.
"""
from bayespd.reference import cantilever, plate_with_hole, three_point_bending
from bayespd.reference.compare import observed_order, pd_versus_fe, relative_l2
from bayespd.reference.fem import BodyLoad, FESolution, Region, Support, isotropic_stiffness, solve_box, solve_mesh
from bayespd.reference.lattice import lattice_stiffness

__all__ = ["cantilever", "plate_with_hole", "three_point_bending", "observed_order", "pd_versus_fe", "relative_l2",
           "BodyLoad", "FESolution", "Region", "Support", "isotropic_stiffness", "solve_box", "solve_mesh",
           "lattice_stiffness"]
