"""EABC: ensemble-based actor-critic with adaptive behaviour cloning, in JAX."""

from eabc.policy import Policy, load_policy

__all__ = ["Policy", "load_policy"]
__version__ = "0.1.0"
