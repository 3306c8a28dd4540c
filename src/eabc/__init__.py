"""EABC: ensemble-based actor-critic with adaptive behaviour cloning, in JAX."""

from __future__ import annotations

__all__ = ["Policy", "load_policy"]
__version__ = "0.1.0"


def __getattr__(name: str):
    """``Policy`` and ``load_policy`` on first use: importing a part of the package (the NumPy
    data makers in their worker processes, say) does not start JAX."""
    if name in __all__:
        from eabc import policy  # noqa: PLC0415 (on first use: importing eabc starts no JAX)

        return getattr(policy, name)
    raise AttributeError(f"module 'eabc' has no attribute {name!r}")
