"""Multi-layer perceptrons in plain JAX: the actor, and critic ensembles as one vectorised network.

Parameters are plain dicts of arrays (``w0, b0, w1, b1, ...``) so that checkpoints are simple and a
NumPy copy of the actor can run evaluation without JAX. Initialisation follows PyTorch's default for
``nn.Linear`` (uniform in +-1/sqrt(fan_in) for weights and biases), as in the reference TD3+BC code.

An ensemble of K networks stores every weight with a leading member axis (``w0: [K, in, out]``) and is
evaluated in one batched matrix product per layer, never a Python loop over members.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from eabc.numpy_networks import LOG_STD_MAX, LOG_STD_MIN
from eabc.numpy_networks import numpy_actor as numpy_actor  # re-exported: evaluation, SAC
from eabc.numpy_networks import numpy_gaussian_sampler as numpy_gaussian_sampler
from eabc.numpy_networks import numpy_mlp as numpy_mlp

Params = dict[str, jax.Array]


def init_mlp(
    key: jax.Array,
    sizes: Sequence[int],
    num_members: int | None = None,
    layer_norm: bool = False,
) -> Params:
    """Initialise an MLP with layer widths ``sizes`` (input first, output last).

    With ``num_members`` set, every array gets a leading ensemble axis and each member is drawn
    independently. With ``layer_norm``, every hidden layer gets a LayerNorm (scale ``g{i}`` = 1,
    offset ``h{i}`` = 0) between its product and its ReLU, as in SEEM and ReBRAC's critics.
    """
    params = {}
    keys = jax.random.split(key, 2 * (len(sizes) - 1))
    lead = () if num_members is None else (num_members,)
    for layer, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        bound = 1.0 / np.sqrt(fan_in)
        params[f"w{layer}"] = jax.random.uniform(
            keys[2 * layer], lead + (fan_in, fan_out), minval=-bound, maxval=bound
        )
        params[f"b{layer}"] = jax.random.uniform(
            keys[2 * layer + 1], lead + (fan_out,), minval=-bound, maxval=bound
        )
        if layer_norm and layer < len(sizes) - 2:
            params[f"g{layer}"] = jnp.ones(lead + (fan_out,))
            params[f"h{layer}"] = jnp.zeros(lead + (fan_out,))
    return params


def num_layers(params: Params) -> int:
    return sum(1 for name in params if name.startswith("w"))


LAYER_NORM_EPS = 1e-5
"""PyTorch's and Flax's LayerNorm epsilon."""


def _layer_norm_stats(h: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Row sums and ``1 / sqrt(var + eps)`` over the last axis; the variance in two passes,
    ``mean((h - mean)^2)``, exact for inputs with a large common offset."""
    width = h.shape[-1]
    total = h.sum(axis=-1, keepdims=True)
    # (h * width - total) = width * (h - mean): the same centring as _normalised's, written apart
    # so that XLA keeps each inside its own fusion instead of storing one shared h-sized array.
    var = jnp.square(h * width - total).sum(axis=-1, keepdims=True) / width**3
    return total, jax.lax.rsqrt(var + LAYER_NORM_EPS)


def _normalised(h: jax.Array, total: jax.Array, rstd: jax.Array) -> jax.Array:
    return (h - total / h.shape[-1]) * rstd


@jax.custom_vjp
def layer_norm_relu(h: jax.Array, scale: jax.Array, offset: jax.Array) -> jax.Array:
    """``relu(LayerNorm(h) * scale + offset)``, normalising over the last axis.

    ``h: [..., B, W]``; ``scale`` and ``offset: [..., 1, W]`` (one per member of an ensemble).
    The same function as LayerNorm then ReLU written out, with a hand-written gradient: XLA on CPU
    turns the automatic one into some 20 passes over ``h``-sized arrays; this one takes about 8
    (``docs/speed.md``).
    """
    total, rstd = _layer_norm_stats(h)
    return jax.nn.relu(_normalised(h, total, rstd) * scale + offset)


def _layer_norm_relu_fwd(h, scale, offset):
    total, rstd = _layer_norm_stats(h)
    xhat = _normalised(h, total, rstd)
    y = jax.nn.relu(xhat * scale + offset)
    return y, (xhat, y, rstd, scale)


def _row_dot(a: jax.Array, v: jax.Array) -> jax.Array:
    """``sum_w a[..., b, w] * v[..., 0, w]`` as a batched matrix-vector product: ``[..., B, 1]``."""
    return jnp.einsum("...bw,...w->...b", a, v[..., 0, :])[..., None]


def _layer_norm_relu_bwd(res, dy):
    # The LayerNorm gradient: with g = dy * relu' * scale, dh = rstd * (g - mean(g) - xhat * mean(g
    # xhat)) per row; scale and offset get the batch sums of dy * relu' * xhat and dy * relu'.
    xhat, y, rstd, scale = res
    width = xhat.shape[-1]
    active = y > 0
    dpre = jnp.where(active, dy, 0.0)  # through the ReLU, as jax.nn.relu's gradient
    dpre_xhat = dpre * xhat
    mean_g = _row_dot(dpre, scale) / width
    mean_g_xhat = _row_dot(dpre_xhat, scale) / width
    # dh ends in a select: YNNPACK fuses no select, so the next product cannot pull this
    # expression into its own (much slower) fusion where dh has no other use.
    dh = jnp.where(
        active,
        rstd * (dy * scale - mean_g - xhat * mean_g_xhat),
        rstd * (-mean_g - xhat * mean_g_xhat),
    )
    return dh, dpre_xhat.sum(axis=-2, keepdims=True), dpre.sum(axis=-2, keepdims=True)


layer_norm_relu.defvjp(_layer_norm_relu_fwd, _layer_norm_relu_bwd)


def _hidden(params: Params, layer: int, h: jax.Array) -> jax.Array:
    """A hidden layer's output after its product: LayerNorm (if the network has one), then ReLU."""
    if f"g{layer}" in params:  # one scale and offset per member: [K, 1, W] against [K, B, W]
        scale, offset = params[f"g{layer}"][..., None, :], params[f"h{layer}"][..., None, :]
        return layer_norm_relu(h, scale, offset)
    return jax.nn.relu(h)


def mlp(params: Params, x: jax.Array) -> jax.Array:
    """ReLU MLP on ``x: [B, in]`` (no activation after the last layer)."""
    n = num_layers(params)
    for layer in range(n):
        x = x @ params[f"w{layer}"] + params[f"b{layer}"]
        if layer < n - 1:
            x = _hidden(params, layer, x)
    return x


def ensemble_mlp(params: Params, x: jax.Array) -> jax.Array:
    """Every member of an ensemble MLP on the same input ``x: [B, in]`` (or member ``k`` on
    ``x[k]`` for ``x: [K, B, in]``); returns ``[K, B, out]``.

    The input is shared, so the first layer is one ``[B, in] x [in, K * out]`` product (15% faster
    per training step on CPU than a batched product with a tiny contraction); later layers are
    batched over the member axis. With LayerNorm the first layer is the batched product instead:
    the normalisation and its gradient read that layer's output several times, and from the one
    product's ``[B, K, W]`` layout XLA reads it transposed each time (8% of a step).
    """
    n = num_layers(params)
    k, fan_in, width = params["w0"].shape
    if x.ndim == 2 and "g0" in params:
        x = jnp.broadcast_to(x, (k, *x.shape))
    if x.ndim == 3:  # one input per member: [K, B, in]
        h = jnp.einsum("kbi,kio->kbo", x, params["w0"]) + params["b0"][:, None, :]
    else:
        w0 = params["w0"].transpose(1, 0, 2).reshape(fan_in, k * width)
        h = (x @ w0).reshape(-1, k, width).transpose(1, 0, 2) + params["b0"][:, None, :]
    for layer in range(1, n):
        h = _hidden(params, layer - 1, h)
        h = jnp.einsum("kbi,kio->kbo", h, params[f"w{layer}"]) + params[f"b{layer}"][:, None, :]
    return h


def actor_apply(params: Params, obs: jax.Array, max_action: float) -> jax.Array:
    """Deterministic actor: ``max_action * tanh(MLP(obs))``."""
    return max_action * jnp.tanh(mlp(params, obs))


def critic_apply(params: Params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Q-values of every ensemble member: ``[K, B]``."""
    return ensemble_mlp(params, jnp.concatenate([obs, action], axis=-1))[..., 0]


def gaussian_actor_apply(params: Params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tanh-Gaussian actor (SAC, CQL, EDAC): the MLP outputs the mean and log-std of ``u``."""
    mean, log_std = jnp.split(mlp(params, obs), 2, axis=-1)
    return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)


def sample_tanh_gaussian(
    key: jax.Array, mean: jax.Array, log_std: jax.Array, max_action: float
) -> tuple[jax.Array, jax.Array]:
    """An action ``max_action * tanh(u)``, ``u ~ N(mean, std)``, and its log-density.

    The change of variables uses ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))``, which is
    exact and stable for large ``|u|``.
    """
    eps = jax.random.normal(key, mean.shape, mean.dtype)
    u = mean + jnp.exp(log_std) * eps
    log_prob = (-0.5 * eps**2 - log_std - 0.5 * np.log(2 * np.pi)).sum(axis=-1)
    log_prob -= (2.0 * (np.log(2.0) - u - jax.nn.softplus(-2.0 * u))).sum(axis=-1)
    log_prob -= mean.shape[-1] * np.log(max_action)
    return max_action * jnp.tanh(u), log_prob


def polyak(target: Params, online: Params, tau: float) -> Params:
    """Soft target update ``target <- tau * online + (1 - tau) * target``."""
    return jax.tree.map(lambda t, o: tau * o + (1.0 - tau) * t, target, online)
