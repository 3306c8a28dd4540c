"""The LayerNorm critics' hand-written gradients against the layers written out and
differentiated by JAX (LayerNorm then ReLU, EABC's; ReLU then LayerNorm, ReBRAC's authors'):
values and gradients, one layer and whole ensembles, large offsets."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eabc import networks
from eabc.agents import eabc
from eabc.agents.common import Batch
from eabc.programs import Program

RTOL = 1e-5


def reference_layer_norm_relu(h, scale, offset):
    """The formula the networks computed before the hand-written gradient (two-pass variance,
    automatic differentiation): what ``networks.layer_norm_relu`` must equal."""
    mean = h.mean(axis=-1, keepdims=True)
    var = ((h - mean) ** 2).mean(axis=-1, keepdims=True)
    h = (h - mean) * jax.lax.rsqrt(var + networks.LAYER_NORM_EPS)
    return jax.nn.relu(h * scale + offset)


def reference_relu_layer_norm(h, scale, offset):
    """ReLU then LayerNorm (Flax's epsilon) written out: what ``networks.relu_layer_norm``, the
    authors' ReBRAC critic layer, must equal."""
    x = jax.nn.relu(h)
    mean = x.mean(axis=-1, keepdims=True)
    var = ((x - mean) ** 2).mean(axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + networks.FLAX_LAYER_NORM_EPS) * scale + offset


def reference_ensemble_mlp(params, x, norm_after_relu=False):
    """``ensemble_mlp`` as it was: one product for the first layer, the reference LayerNorm."""
    hidden = reference_relu_layer_norm if norm_after_relu else reference_layer_norm_relu
    n = networks.num_layers(params)
    k, fan_in, width = params["w0"].shape
    if x.ndim == 3:
        h = jnp.einsum("kbi,kio->kbo", x, params["w0"]) + params["b0"][:, None, :]
    else:
        w0 = params["w0"].transpose(1, 0, 2).reshape(fan_in, k * width)
        h = (x @ w0).reshape(-1, k, width).transpose(1, 0, 2) + params["b0"][:, None, :]
    for layer in range(1, n):
        scale, offset = params[f"g{layer - 1}"], params[f"h{layer - 1}"]
        h = hidden(h, scale[:, None, :], offset[:, None, :])
        h = jnp.einsum("kbi,kio->kbo", h, params[f"w{layer}"]) + params[f"b{layer}"][:, None, :]
    return h


def assert_close(got, want, rtol=RTOL):
    """Elementwise within ``rtol`` of the larger of the value and the array's typical size (the
    two sum in different orders, so entries near zero differ by a few float32 ulps of the
    rest)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape
    scale = np.maximum(np.abs(want), np.sqrt(np.mean(want**2)) + 1e-30)
    assert np.max(np.abs(got - want) / scale) <= rtol, np.max(np.abs(got - want) / scale)


def value_and_grads(fn, args, cotangent):
    """``fn(*args)`` and the gradient of ``<fn(*args), cotangent>`` with respect to every arg,
    both compiled (as training runs them)."""
    out = jax.jit(fn)(*args)
    grads = jax.jit(jax.grad(lambda *a: jnp.vdot(fn(*a), cotangent), range(len(args))))(*args)
    return out, grads


def normal(seed, shape, scale=1.0):
    """Float32 Gaussian test inputs from NumPy: eager jax.random would compile a program per shape,
    most of these tests' time."""
    return (scale * np.random.default_rng(seed).standard_normal(shape)).astype(np.float32)


def random_layer(seed, shape, offset_size):
    """``h`` with a common offset per row of ``offset_size`` (the one-pass variance's worst case),
    scale around 1 with some signs flipped, offset around 0: some units inactive."""
    rng = np.random.default_rng(seed)
    side = (*shape[:-2], 1, shape[-1])
    h = 2.0 * rng.standard_normal(shape) + offset_size * rng.uniform(0.5, 1.0, (*shape[:-1], 1))
    scale = 1.0 + 0.5 * rng.standard_normal(side)
    offset = 0.5 * rng.standard_normal(side)
    args = tuple(jnp.asarray(a, jnp.float32) for a in (h, scale, offset))
    return args, jnp.asarray(rng.standard_normal(shape), jnp.float32)


@pytest.mark.parametrize("offset_size", [0.0, 30.0])
@pytest.mark.parametrize("shape", [(10, 64, 256), (32, 48), (3, 16, 7)])
def test_layer_norm_relu_equals_the_formula_in_value_and_gradient(shape, offset_size):
    args, cotangent = random_layer(len(shape) + int(offset_size), shape, offset_size)
    got, got_grads = value_and_grads(networks.layer_norm_relu, args, cotangent)
    want, want_grads = value_and_grads(reference_layer_norm_relu, args, cotangent)
    assert 0.2 < float(jnp.mean(want > 0)) < 0.8  # both sides of the ReLU are exercised
    assert_close(got, want)
    for g, w in zip(got_grads, want_grads):
        assert_close(g, w)


@pytest.mark.parametrize("offset_size", [0.0, 30.0])
@pytest.mark.parametrize("shape", [(10, 64, 256), (32, 48), (3, 16, 7)])
def test_relu_layer_norm_equals_the_formula_in_value_and_gradient(shape, offset_size):
    args, cotangent = random_layer(len(shape) + int(offset_size), shape, offset_size)
    got, got_grads = value_and_grads(networks.relu_layer_norm, args, cotangent)
    want, want_grads = value_and_grads(reference_relu_layer_norm, args, cotangent)
    assert 0.2 < float(jnp.mean(args[0] > 0)) <= 1.0
    assert_close(got, want)
    for g, w in zip(got_grads, want_grads):
        assert_close(g, w)


def test_relu_layer_norm_of_a_row_without_active_unit_is_its_offset():
    """Every unit of a row at or below 0: the normalised row is 0 (epsilon keeps it finite), the
    output the offset, and no gradient reaches h."""
    h = -jnp.abs(jnp.asarray(normal(11, (2, 4, 8)))).at[1].set(1.0 + jnp.arange(8.0))
    scale, offset = jnp.full((2, 1, 8), 2.0), jnp.asarray(normal(12, (2, 1, 8)))
    out = networks.relu_layer_norm(h, scale, offset)
    np.testing.assert_array_equal(out[0], jnp.broadcast_to(offset[0], (4, 8)))
    grad = jax.grad(lambda h: networks.relu_layer_norm(h, scale, offset).sum() ** 2)(h)
    assert bool(jnp.all(grad[0] == 0)) and bool(jnp.all(jnp.isfinite(grad)))


def float64_layer_norm_relu(h, scale, offset, cotangent, active):
    """Value and gradients (h, scale, offset) of ``<relu(LayerNorm(h) scale + offset), cot>``
    in float64 NumPy, the textbook gradient (checked against finite differences below); the
    ReLU's gradient passes where ``active`` (float32 and float64 may disagree on which side of
    the kink a unit lies, and there the gradients differ entirely)."""
    h, scale, offset, cotangent = (np.asarray(a, np.float64) for a in (h, scale, offset, cotangent))
    xhat = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + 1e-5)
    pre = xhat * scale + offset
    dpre = np.where(active, cotangent, 0.0)
    g = dpre * scale
    dh = (g - g.mean(-1, keepdims=True) - xhat * (g * xhat).mean(-1, keepdims=True)) / np.sqrt(
        h.var(-1, keepdims=True) + 1e-5
    )
    return np.maximum(pre, 0.0), (
        dh,
        (dpre * xhat).sum(-2, keepdims=True),
        dpre.sum(-2, keepdims=True),
    )


def relative_error(got, want):
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return np.max(np.abs(got - want) / np.maximum(np.abs(want), np.sqrt(np.mean(want**2))))


@pytest.mark.parametrize("shape", [(10, 64, 256), (32, 48), (3, 16, 7)])
def test_large_offsets_lose_no_more_than_the_formula(shape):
    """Rows offset by 500 of their standard deviations: float32 inputs then carry only about 4
    significant digits of their spread, so both versions are off the exact answer by about 1e-4,
    and may differ from each other by as much. A one-pass variance (E[h^2] - E[h]^2) would be off
    by 100% here; the shifted one must be about as close to the float64 answer as the formula.
    A unit within that error of the ReLU's kink may lie on either side of it in the two: each is
    held to the float64 gradient on its own side."""
    args, cotangent = random_layer(len(shape), shape, 1000.0)
    got, got_grads = value_and_grads(networks.layer_norm_relu, args, cotangent)
    want, want_grads = value_and_grads(reference_layer_norm_relu, args, cotangent)
    exact, exact_grads = float64_layer_norm_relu(*args, cotangent, np.asarray(want) > 0)
    ours, our_grads = float64_layer_norm_relu(*args, cotangent, np.asarray(got) > 0)
    for name, g, w, e, o in zip(
        ("value", "h", "scale", "offset"),
        (got, *got_grads),
        (want, *want_grads),
        (exact, *exact_grads),
        (ours, *our_grads),
    ):
        assert relative_error(g, o) <= 3 * relative_error(w, e) + 1e-6, name
        assert relative_error(g, o) < 1e-3, name


def test_layer_norm_relu_gradient_matches_finite_differences():
    (h, scale, offset), cotangent = random_layer(7, (2, 5, 6), 3.0)
    h, scale, offset, cotangent = (np.asarray(a, np.float64) for a in (h, scale, offset, cotangent))

    def loss(h):  # float64 NumPy: LayerNorm then ReLU, summed against the cotangent
        mean = h.mean(-1, keepdims=True)
        x = (h - mean) / np.sqrt(h.var(-1, keepdims=True) + networks.LAYER_NORM_EPS)
        return np.sum(np.maximum(x * scale + offset, 0.0) * cotangent)

    eps, numeric = 1e-6, np.zeros_like(h)
    for index in np.ndindex(h.shape):
        step = np.zeros_like(h)
        step[index] = eps
        numeric[index] = (loss(h + step) - loss(h - step)) / (2 * eps)
    grad = jax.grad(lambda h: jnp.vdot(networks.layer_norm_relu(h, scale, offset), cotangent))
    np.testing.assert_allclose(grad(jnp.asarray(h, jnp.float32)), numeric, rtol=2e-3, atol=2e-4)


def layer_norm_critic(seed, k, sizes, bias_offset):
    """An ensemble with LayerNorm whose scales, offsets and biases are not at their initial values
    (``bias_offset`` shifts every hidden pre-activation by a common amount); ``init_mlp``'s
    shapes, NumPy's numbers."""
    shapes = jax.eval_shape(lambda: networks.init_mlp(jax.random.PRNGKey(0), sizes, k, True))
    rng, params = np.random.default_rng(seed), {}
    for name, shape in shapes.items():
        noise = rng.standard_normal(shape.shape)
        if name[0] == "w":
            params[name] = noise / np.sqrt(shape.shape[-2])
        elif name[0] == "g":
            params[name] = 1.0 + 0.5 * noise
        else:
            params[name] = 0.3 * noise
        if name[0] == "b" and name != f"b{len(sizes) - 2}":
            params[name] = params[name] + bias_offset
    return {name: jnp.asarray(p, jnp.float32) for name, p in params.items()}


@pytest.mark.parametrize("norm_after_relu", [False, True])
@pytest.mark.parametrize("bias_offset", [0.0, 20.0])
@pytest.mark.parametrize("per_member_input", [False, True])
def test_ensemble_equals_the_formula_in_value_and_gradient(
    bias_offset, per_member_input, norm_after_relu
):
    k, obs_act, batch = 10, 14, 64
    params = layer_norm_critic(1, k, (obs_act, 256, 256, 1), bias_offset)
    shape = (k, batch, obs_act) if per_member_input else (batch, obs_act)
    x = jnp.asarray(normal(2, shape, 2.0))
    cotangent = jnp.asarray(normal(3, (k, batch, 1)))
    got, (got_params, got_x) = value_and_grads(
        lambda p, x: networks.ensemble_mlp(p, x, norm_after_relu), (params, x), cotangent
    )
    want, (want_params, want_x) = value_and_grads(
        lambda p, x: reference_ensemble_mlp(p, x, norm_after_relu), (params, x), cotangent
    )
    # Pre-activations offset by 20 (about 15 of their standard deviations): the one-pass and
    # two-pass variances round differently, each a few 1e-6 from float64 per layer.
    rtol = RTOL if bias_offset == 0 else 3 * RTOL
    assert_close(got, want, rtol)
    assert_close(got_x, want_x, rtol)
    assert got_params.keys() == want_params.keys()
    for name in want_params:
        assert_close(got_params[name], want_params[name], rtol)


def test_single_network_and_vmapped_seeds_equal_the_formula():
    """``mlp`` with LayerNorm (scales of shape [W]) and an ensemble vmapped over seeds, as
    ``train_chunk_seeds`` runs it."""
    shapes = jax.eval_shape(
        lambda: networks.init_mlp(jax.random.PRNGKey(0), (5, 32, 32, 3), None, True)
    )
    params = {
        n: jnp.asarray(normal(i, s.shape, 0.3)) + (n[0] == "g")
        for i, (n, s) in enumerate(shapes.items())
    }
    x = jnp.asarray(normal(5, (16, 5)))

    def reference_mlp(params, x):
        for layer in range(3):
            x = x @ params[f"w{layer}"] + params[f"b{layer}"]
            if layer < 2:
                x = reference_layer_norm_relu(x, params[f"g{layer}"], params[f"h{layer}"])
        return x

    cotangent = jnp.asarray(normal(6, (16, 3)))
    got, got_grads = value_and_grads(networks.mlp, (params, x), cotangent)
    want, want_grads = value_and_grads(reference_mlp, (params, x), cotangent)
    assert_close(got, want)
    for g, w in zip(jax.tree.leaves(got_grads), jax.tree.leaves(want_grads)):
        assert_close(g, w)

    seeds = jax.tree.map(
        lambda *p: jnp.stack(p),
        *(layer_norm_critic(8 + s, 4, (6, 16, 16, 1), 0.0) for s in range(3)),
    )
    x = jnp.asarray(normal(9, (3, 8, 6)))
    cotangent = jnp.asarray(normal(10, (3, 4, 8, 1)))
    vmapped = lambda f: jax.vmap(f)  # noqa: E731
    got, got_grads = value_and_grads(vmapped(networks.ensemble_mlp), (seeds, x), cotangent)
    want, want_grads = value_and_grads(vmapped(reference_ensemble_mlp), (seeds, x), cotangent)
    assert_close(got, want)
    for g, w in zip(jax.tree.leaves(got_grads), jax.tree.leaves(want_grads)):
        assert_close(g, w)


@pytest.mark.parametrize(
    "sizes, members, layer_norm, hidden_bias, output_bound",
    [((5, 16, 16, 3), None, False, None, None), ((4, 8, 8, 8, 1), 3, True, 0.1, 3e-3)],
)
def test_an_eagerly_drawn_network_is_the_one_drawn_inside_a_program(
    sizes, members, layer_norm, hidden_bias, output_bound
):
    """Called outside any program, ``init_mlp`` runs one program of its own, compiled with
    the init options; inside a jit or a vmap it is traced into the caller's. Same bits."""
    draw = functools.partial(
        networks.init_mlp, sizes=sizes, num_members=members, layer_norm=layer_norm,
        hidden_bias=hidden_bias, output_bound=output_bound,
    )  # fmt: skip
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    eager = draw(keys[0])
    traced = jax.jit(draw)(keys[0])
    # Under vmap in a program of its own, built quickly (the default build is the line above).
    vmap = Program(jax.vmap(draw), networks.INIT_COMPILE_OPTIONS)
    vmapped = jax.tree.map(lambda x: x[0], vmap(keys))
    assert set(eager) == set(traced) == set(vmapped)
    for name in eager:
        np.testing.assert_array_equal(np.asarray(eager[name]), np.asarray(traced[name]), name)
        np.testing.assert_array_equal(np.asarray(eager[name]), np.asarray(vmapped[name]), name)
    assert networks._draw_mlp_compiled._cache_size() >= 1  # the eager call ran its own program


def test_nan_inputs_stay_nan():
    """A diverged pre-activation must not be hidden: the run's NaN check reads the Q values."""
    h = jnp.ones((2, 3, 8)).at[0, 1, 2].set(jnp.nan)
    out = networks.layer_norm_relu(h, jnp.ones((2, 1, 8)), jnp.zeros((2, 1, 8)))
    assert bool(jnp.all(jnp.isnan(out[0, 1]))) and not bool(jnp.any(jnp.isnan(out[1])))


def test_an_eabc_ln_step_equals_the_two_pass_formulas_to_float_tolerance(monkeypatch):
    """The one-pass statistics change eabc-ln's trajectory in the last bits of each step (Adam
    then grows them, as it grows any rounding): its critics' and actor's gradients against the
    layer written out with two-pass statistics and differentiated by JAX."""
    config = eabc.PRESETS["eabc-ln"]
    rng = np.random.default_rng(0)
    state = eabc.init(jax.random.PRNGKey(0), 11, 3, config)
    batch = Batch(
        *(jnp.asarray(a, jnp.float32) for a in (
            rng.normal(size=(64, 11)), rng.uniform(-1, 1, (64, 3)), rng.normal(size=64),
            rng.normal(size=(64, 11)), np.zeros(64),
        ))
    )  # fmt: skip
    key = jax.random.PRNGKey(1)

    def gradients():
        critic = jax.grad(eabc.critic_loss, has_aux=True)(
            state.critic, state.critic_target, state.actor_target, batch, key, config, 1.0
        )[0]
        actor = jax.grad(eabc.actor_loss, has_aux=True)(
            state.actor, state.critic, batch, key, config, 1.0
        )[0]
        return critic, actor

    got = jax.jit(gradients)()
    monkeypatch.setattr(networks, "layer_norm_relu", reference_layer_norm_relu)
    want = jax.jit(gradients)()
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        assert_close(g, w)
