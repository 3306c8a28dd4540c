"""NumPy copies of the actors, without JAX: evaluation, rollouts and the processes that make
datasets (:mod:`eabc.data.parallel`) act with them and start without JAX's runtime."""

from __future__ import annotations

import numpy as np

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
"""Range of the Gaussian actor's log standard deviation."""


def numpy_mlp(params: dict[str, np.ndarray]):
    """A NumPy copy of an MLP for fast single-observation inference (evaluation, rollouts).

    It computes in float64 from float32 weights, so that its float32-rounded results do not depend
    on the order in which the CPU's BLAS kernel sums (OpenBLAS picks kernels by CPU; in float32 a
    1,000-step rollout, and so a generated dataset, differed between two of them).
    """
    if any(name.startswith("g") for name in params):
        raise ValueError("numpy_mlp runs actors, which have no LayerNorm")
    weights = [
        (np.asarray(params[f"w{i}"], np.float32).astype(np.float64),
         np.asarray(params[f"b{i}"], np.float32).astype(np.float64))
        for i in range(len(params) // 2)
    ]  # fmt: skip

    def apply(obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, np.float64)
        for i, (w, b) in enumerate(weights):
            x = x @ w + b
            if i < len(weights) - 1:
                np.maximum(x, 0.0, out=x)
        return x

    return apply


def numpy_actor(params: dict[str, np.ndarray], max_action: float, gaussian: bool = False):
    """The deterministic action of an actor in NumPy: ``max_action * tanh(out)``.

    For a Gaussian actor (``gaussian=True``) ``out`` is the mean, the first half of the outputs.
    """
    apply = numpy_mlp(params)

    def act(obs: np.ndarray) -> np.ndarray:
        out = apply(obs)
        if gaussian:
            out = out[..., : out.shape[-1] // 2]
        return (max_action * np.tanh(out)).astype(np.float32)

    return act


def numpy_gaussian_sampler(params: dict[str, np.ndarray], max_action: float):
    """Sample ``max_action * tanh(u)``, ``u ~ N(mean, std)``, in NumPy: acting while collecting data."""
    apply = numpy_mlp(params)

    def sample(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        mean, log_std = np.split(apply(obs), 2, axis=-1)
        log_std = np.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)
        u = mean + np.exp(log_std) * rng.standard_normal(mean.shape, dtype=np.float32)
        return (max_action * np.tanh(u)).astype(np.float32)

    return sample
