"""ReBRAC as its authors run it (tinkoff-ai/ReBRAC's code and configs, CORL's copy of them): the
betas per dataset with their sources, raw observations, the critics' LayerNorm after the ReLU,
EDAC's initialisation, and every other algorithm's networks unchanged by these options."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eabc import networks
from eabc.agents import eabc, get_algorithm, rebrac, td3_core
from eabc.training import lifecycle
from eabc.training.config import TrainConfig, resolve_agent_config

OBS, ACT = 11, 3

# Table 11 of the paper, all 15 Gym-MuJoCo datasets. CORL's configs/offline/rebrac/*/*_v2.yaml
# agree but for hopper-medium and hopper-expert (beta_2 0.01 and 0.1); for hopper-medium the
# authors' released configs/rebrac/hopper/hopper_medium.yaml has the paper's 0.001.
TABLE_11 = {
    "halfcheetah-random": (0.001, 0.1),
    "halfcheetah-medium": (0.001, 0.01),
    "halfcheetah-expert": (0.01, 0.01),
    "halfcheetah-medium-expert": (0.01, 0.1),
    "halfcheetah-medium-replay": (0.01, 0.001),
    "hopper-random": (0.001, 0.01),
    "hopper-medium": (0.01, 0.001),
    "hopper-expert": (0.1, 0.001),
    "hopper-medium-expert": (0.1, 0.01),
    "hopper-medium-replay": (0.05, 0.5),
    "walker2d-random": (0.01, 0.0),
    "walker2d-medium": (0.05, 0.1),
    "walker2d-expert": (0.01, 0.5),
    "walker2d-medium-expert": (0.01, 0.01),
    "walker2d-medium-replay": (0.05, 0.01),
}


@pytest.mark.parametrize(("name", "betas"), sorted(TABLE_11.items()))
def test_betas_per_dataset_are_table_11s(name, betas):
    config = resolve_agent_config("rebrac", name, {})
    assert (config.actor_bc_weight, config.critic_bc_weight) == betas


def _start(tmp_path, dataset, algo, overrides):
    config = TrainConfig(dataset="pendulum-swingup", algo=algo, env="Pendulum-v1")
    run = lifecycle.start(config, tmp_path / algo, {"hidden_dims": (8, 8), **overrides}, dataset)
    run.lock.release()
    return run


def test_rebrac_trains_and_acts_on_raw_observations(tmp_path, pendulum_dataset):
    """The authors' configs all have normalize_states: false; every other algorithm keeps
    TD3+BC's normaliser."""
    betas = {"actor_bc_weight": 0.1, "critic_bc_weight": 0.01}
    assert not get_algorithm("rebrac").normalize_observations
    run = _start(tmp_path, pendulum_dataset, "rebrac", betas)
    np.testing.assert_array_equal(run.normalizer.mean, np.zeros(3, np.float32))
    np.testing.assert_array_equal(run.normalizer.std, np.ones(3, np.float32))
    obs = pendulum_dataset.observations[:5]
    np.testing.assert_array_equal(run.normalizer(obs), obs)
    other = _start(tmp_path, pendulum_dataset, "td3bc", {})
    assert get_algorithm("td3bc").normalize_observations
    want = pendulum_dataset.observations.mean(0, dtype=np.float64)
    np.testing.assert_allclose(other.normalizer.mean, want, rtol=1e-6, atol=1e-6)
    assert not np.allclose(other.normalizer.std, 1.0)


def np_critic(params, x, after_relu: bool, eps: float):
    """One member of a LayerNorm critic in float64 NumPy, the authors' layer order when
    ``after_relu`` (Dense, ReLU, LayerNorm), else ours (Dense, LayerNorm, ReLU)."""
    p = {name: np.asarray(v, np.float64) for name, v in params.items()}
    x = np.asarray(x, np.float64)
    n = sum(name.startswith("w") for name in p)

    def norm(x, layer):
        x = (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + eps)
        return x * p[f"g{layer}"] + p[f"h{layer}"]

    for layer in range(n):
        x = x @ p[f"w{layer}"] + p[f"b{layer}"]
        if layer < n - 1:
            x = norm(np.maximum(x, 0.0), layer) if after_relu else np.maximum(norm(x, layer), 0.0)
    return x[:, 0]


def scrambled_critic(seed, k=3, sizes=(OBS + ACT, 32, 32, 1)):
    """A LayerNorm ensemble with scales, offsets and biases away from their initial values."""
    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(lambda: networks.init_mlp(jax.random.PRNGKey(0), sizes, k, True))
    params = {}
    for name, shape in shapes.items():
        noise = rng.standard_normal(shape.shape)
        if name[0] == "w":
            params[name] = noise / np.sqrt(shape.shape[-2])
        else:  # LayerNorm scales around 1; offsets and biases around 0
            params[name] = (name[0] == "g") + 0.3 * noise
    return {name: jnp.asarray(p, jnp.float32) for name, p in params.items()}


@pytest.mark.parametrize("after_relu", [True, False])
def test_critic_layer_norm_sits_where_the_setting_puts_it(after_relu):
    critic = scrambled_critic(0)
    rng = np.random.default_rng(1)
    obs, act = rng.normal(size=(16, OBS)), rng.uniform(-1, 1, size=(16, ACT))
    placement = "after-relu" if after_relu else "before-relu"
    config = dataclasses.replace(rebrac.PRESETS["rebrac"], layer_norm_placement=placement)
    got = rebrac._q(critic, jnp.asarray(obs, jnp.float32), jnp.asarray(act, jnp.float32), config)
    eps = 1e-6 if after_relu else 1e-5  # Flax's LayerNorm, the authors'; PyTorch's, SEEM's
    sa = np.concatenate([obs, act], -1)
    want = np.stack([np_critic({n: v[i] for n, v in critic.items()}, sa, after_relu, eps)
                     for i in range(3)])  # fmt: skip
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-6)
    other = np.stack([np_critic({n: v[i] for n, v in critic.items()}, sa, not after_relu, eps)
                      for i in range(3)])  # fmt: skip
    assert np.abs(other - want).max() > 1e-2, "the two placements must differ in this test"
    assert rebrac.PRESETS["rebrac"].layer_norm_placement == "after-relu"


def test_initialisation_is_edacs():
    """Hidden biases 0.1, output layers uniform in +-1e-3 (actor) and +-3e-3 (critics),
    PyTorch's uniform +-1/sqrt(fan_in) hidden weights: the authors' networks.py."""
    state = rebrac.init(jax.random.PRNGKey(0), OBS, ACT, rebrac.PRESETS["rebrac"])
    for net, bound, lead in ((state.actor, 1e-3, ()), (state.critic, 3e-3, (2,))):
        for layer, fan_in in enumerate((net["w0"].shape[-2], 256, 256)):
            assert net[f"b{layer}"].shape == (*lead, 256)
            np.testing.assert_array_equal(net[f"b{layer}"], np.full((*lead, 256), 0.1, np.float32))
            w = np.abs(np.asarray(net[f"w{layer}"]))
            assert 0.95 / np.sqrt(fan_in) < w.max() <= 1 / np.sqrt(fan_in)
        for name in ("w3", "b3"):
            out = np.abs(np.asarray(net[name]))
            assert 0.5 * bound < out.max() <= bound, (name, out.max())
    assert not np.array_equal(state.critic["w3"][0], state.critic["w3"][1]), "members differ"
    for name in state.actor:  # the targets start as copies
        np.testing.assert_array_equal(state.actor_target[name], state.actor[name])


def reference_init(key, sizes, num_members=None, layer_norm=False):
    """PyTorch's default initialisation as init_mlp drew it before the options existed."""
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


@pytest.mark.parametrize("preset", ["eabc", "eabc-ln", "td3bc"])
def test_other_algorithms_start_from_the_same_bits(preset):
    config = dataclasses.replace(eabc.PRESETS[preset], num_critics=3, hidden_dims=(16, 16))
    state = td3_core.init(jax.random.PRNGKey(4), OBS, ACT, config)
    actor_key, critic_key = jax.random.split(jax.random.PRNGKey(4))
    want_actor = reference_init(actor_key, (OBS, 16, 16, ACT))
    want_critic = reference_init(
        critic_key, (OBS + ACT, 16, 16, 1), 3, config.critic_layer_norm
    )  # fmt: skip
    for got, want in ((state.actor, want_actor), (state.critic, want_critic)):
        assert got.keys() == want.keys()
        for name in want:
            np.testing.assert_array_equal(got[name], want[name])
    pytorch = dataclasses.replace(rebrac.PRESETS["rebrac"], initialisation="pytorch")
    state = rebrac.init(jax.random.PRNGKey(4), OBS, ACT, pytorch)
    want = reference_init(critic_key, (OBS + ACT, 256, 256, 256, 1), 2, True)
    for name in want:
        np.testing.assert_array_equal(state.critic[name], want[name])
