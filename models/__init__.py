"""Pyro probabilistic programs, one per calibration problem, written against bayespd's public API."""
