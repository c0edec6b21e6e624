"""Drift controller: vehicle and tyre model, equilibrium maps, reference selector, NMPC."""
