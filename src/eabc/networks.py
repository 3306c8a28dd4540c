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

from eabc import programs
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
    hidden_bias: float | None = None,
    output_bound: float | None = None,
) -> Params:
    """Initialise an MLP with layer widths ``sizes`` (input first, output last).

    With ``num_members`` set, every array gets a leading ensemble axis and each member is drawn
    independently. With ``layer_norm``, every hidden layer gets a LayerNorm (scale ``g{i}`` = 1,
    offset ``h{i}`` = 0); where it sits is the forward pass's choice (:func:`ensemble_mlp`).
    ``hidden_bias`` starts every hidden bias at that constant and ``output_bound`` draws the last
    layer's weights and bias uniform in +-``output_bound`` (EDAC's initialisation, which ReBRAC's
    authors use: 0.1, and 1e-3 for an actor, 3e-3 for critics); None keeps PyTorch's default.
    """
    sizes = tuple(int(size) for size in sizes)
    static = (sizes, num_members, layer_norm, hidden_bias, output_bound)
    if isinstance(key, jax.core.Tracer):  # drawn inside a program being traced: part of it
        return _draw_mlp(key, *static)
    return _draw_mlp_compiled(key, *static)


INIT_COMPILE_OPTIONS = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}
"""How programs that run once (initial parameters) are compiled: LLVM's O1 and XLA's older
fusion emitter give the same parameters bit for bit as XLA's defaults (``tests/test_networks.py``,
``tests/training/test_training.py``), compiled in about half the time at O1 and in 38% less
again with the older emitter (the trainer's ``lifecycle.init_agent`` for all 21 algorithms: 40.8
-> 25.2 s of CPU). A jaxlib that lacks one of them compiles without it (:mod:`eabc.programs`)."""


def _draw_mlp(key, sizes, num_members, layer_norm, hidden_bias, output_bound) -> Params:
    params = {}
    keys = jax.random.split(key, 2 * (len(sizes) - 1))
    lead = () if num_members is None else (num_members,)
    last = len(sizes) - 2
    for layer, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        bound = 1.0 / np.sqrt(fan_in)
        if layer == last and output_bound is not None:
            bound = output_bound
        params[f"w{layer}"] = jax.random.uniform(
            keys[2 * layer], lead + (fan_in, fan_out), minval=-bound, maxval=bound
        )
        if layer < last and hidden_bias is not None:
            params[f"b{layer}"] = jnp.full(lead + (fan_out,), hidden_bias, jnp.float32)
        else:
            params[f"b{layer}"] = jax.random.uniform(
                keys[2 * layer + 1], lead + (fan_out,), minval=-bound, maxval=bound
            )
        if layer_norm and layer < last:
            params[f"g{layer}"] = jnp.ones(lead + (fan_out,))
            params[f"h{layer}"] = jnp.zeros(lead + (fan_out,))
    return params


# Called outside any program (the Python API, the tests): one program per network shape. Drawn
# eagerly, each layer's weights and biases were a program of their own, a few tenths of a second
# each to compile on a CPU; every algorithm's eager init at small sizes took 17.8 s of CPU, now
# 10.3 (one Zen 4 core, no compile cache).
_draw_mlp_compiled = programs.Program(
    _draw_mlp, INIT_COMPILE_OPTIONS, static_argnums=(1, 2, 3, 4, 5)
)


def num_layers(params: Params) -> int:
    return sum(1 for name in params if name.startswith("w"))


LAYER_NORM_EPS = 1e-5
"""PyTorch's LayerNorm epsilon (SEEM's critics; EABC's LayerNorm variant)."""
FLAX_LAYER_NORM_EPS = 1e-6
"""Flax's ``nn.LayerNorm`` epsilon, that of ReBRAC's authors' critics (LayerNorm after the ReLU)."""


def _layer_norm_stats(h: jax.Array, eps: float = LAYER_NORM_EPS) -> tuple[jax.Array, jax.Array]:
    """Row means and ``1 / sqrt(var + eps)`` over the last axis, in one pass: the sums of ``d``
    and ``d^2`` for ``d = h - h[..., :1]``, each row shifted by its first entry. The shift takes a
    common offset out before any square (the textbook one-pass ``E[h^2] - E[h]^2`` loses all
    digits to a large one), and no entry lies more than ``sqrt(width)`` standard deviations from
    its row's mean, so ``mean(d^2) - mean(d)^2`` loses at most ``log10(width)`` digits of the
    variance. Two passes (the mean, then the squares about it) read ``h`` once more, and made an
    eabc-ln step about 5% slower on CPU (docs/speed.md)."""
    width = h.shape[-1]
    shift = h[..., :1]
    d = h - shift
    mean_d = d.sum(axis=-1, keepdims=True) / width
    var = jnp.maximum(jnp.square(d).sum(axis=-1, keepdims=True) / width - jnp.square(mean_d), 0.0)
    return shift + mean_d, jax.lax.rsqrt(var + eps)


def _normalised(h: jax.Array, mean: jax.Array, rstd: jax.Array) -> jax.Array:
    return (h - mean) * rstd


@jax.custom_vjp
def layer_norm_relu(h: jax.Array, scale: jax.Array, offset: jax.Array) -> jax.Array:
    """``relu(LayerNorm(h) * scale + offset)``, normalising over the last axis.

    ``h: [..., B, W]``; ``scale`` and ``offset: [..., 1, W]`` (one per member of an ensemble).
    The same function as LayerNorm then ReLU written out, with a hand-written gradient: XLA on CPU
    turns the automatic one into some 20 passes over ``h``-sized arrays; this one takes about 8
    (``docs/speed.md``).
    """
    mean, rstd = _layer_norm_stats(h)
    return jax.nn.relu(_normalised(h, mean, rstd) * scale + offset)


def _layer_norm_relu_fwd(h, scale, offset):
    mean, rstd = _layer_norm_stats(h)
    xhat = _normalised(h, mean, rstd)
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


@jax.custom_vjp
def relu_layer_norm(h: jax.Array, scale: jax.Array, offset: jax.Array) -> jax.Array:
    """``LayerNorm(relu(h)) * scale + offset`` with Flax's epsilon, normalising over the last
    axis: ReBRAC's authors' hidden layer (Dense, ReLU, LayerNorm), with a hand-written gradient
    as :func:`layer_norm_relu`'s. Shapes as there."""
    x = jax.nn.relu(h)
    mean, rstd = _layer_norm_stats(x, FLAX_LAYER_NORM_EPS)
    return _normalised(x, mean, rstd) * scale + offset


def _relu_layer_norm_fwd(h, scale, offset):
    x = jax.nn.relu(h)
    mean, rstd = _layer_norm_stats(x, FLAX_LAYER_NORM_EPS)
    xhat = _normalised(x, mean, rstd)
    return xhat * scale + offset, (xhat, h, rstd, scale)


def _relu_layer_norm_bwd(res, dy):
    # The LayerNorm gradient of g = dy * scale as in _layer_norm_relu_bwd, then through the ReLU.
    xhat, h, rstd, scale = res
    width = xhat.shape[-1]
    mean_g = _row_dot(dy, scale) / width
    mean_g_xhat = _row_dot(dy * xhat, scale) / width
    dh = jnp.where(h > 0, rstd * (dy * scale - mean_g - xhat * mean_g_xhat), 0.0)
    return dh, (dy * xhat).sum(axis=-2, keepdims=True), dy.sum(axis=-2, keepdims=True)


relu_layer_norm.defvjp(_relu_layer_norm_fwd, _relu_layer_norm_bwd)


def _hidden(params: Params, layer: int, h: jax.Array, norm_after_relu: bool = False) -> jax.Array:
    """A hidden layer's output after its product: ReLU, with the network's LayerNorm (if it has
    one) before it or, with ``norm_after_relu``, after it."""
    if f"g{layer}" in params:  # one scale and offset per member: [K, 1, W] against [K, B, W]
        scale, offset = params[f"g{layer}"][..., None, :], params[f"h{layer}"][..., None, :]
        if norm_after_relu:
            return relu_layer_norm(h, scale, offset)
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


def ensemble_mlp(params: Params, x: jax.Array, norm_after_relu: bool = False) -> jax.Array:
    """Every member of an ensemble MLP on the same input ``x: [B, in]`` (or member ``k`` on
    ``x[k]`` for ``x: [K, B, in]``); returns ``[K, B, out]``. Its LayerNorms (if it has them) sit
    before each hidden ReLU, or after it with ``norm_after_relu`` (:func:`_hidden`).

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
        h = _hidden(params, layer - 1, h, norm_after_relu)
        h = jnp.einsum("kbi,kio->kbo", h, params[f"w{layer}"]) + params[f"b{layer}"][:, None, :]
    return h


def actor_apply(params: Params, obs: jax.Array, max_action: float) -> jax.Array:
    """Deterministic actor: ``max_action * tanh(MLP(obs))``."""
    return max_action * jnp.tanh(mlp(params, obs))


def critic_apply(
    params: Params, obs: jax.Array, action: jax.Array, norm_after_relu: bool = False
) -> jax.Array:
    """Q-values of every ensemble member: ``[K, B]`` (``norm_after_relu``: :func:`ensemble_mlp`)."""
    x = jnp.concatenate([obs, action], axis=-1)
    return ensemble_mlp(params, x, norm_after_relu)[..., 0]


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
