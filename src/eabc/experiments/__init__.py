"""Experiments at scale: sweeps, the results store and the paper-style reports."""
