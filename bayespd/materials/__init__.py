"""Peridynamic material laws behind one contract (``base.Material``): one file per law.

Adding a law is one file here and one export below (``conical.py`` is the example)."""
from bayespd.materials.base import Force, Material
from bayespd.materials.checks import (NonFiniteParameterError, ParameterRangeError, check_modulus,
                                      moduli_from_young, young_from_moduli)
from bayespd.materials.conical import ConicalBondBased
from bayespd.materials.lps import LPS, LPSForce
from bayespd.materials.pmb import BondBased, PMBForce

__all__ = ["Material", "Force", "LPS", "LPSForce", "BondBased", "PMBForce", "ConicalBondBased",
           "ParameterRangeError", "NonFiniteParameterError", "check_modulus", "moduli_from_young",
           "young_from_moduli"]
