"""ReBRAC (Tarasov et al., NeurIPS 2023, "Revisiting the Minimalist Approach to Offline RL"):
TD3+BC with deeper networks, LayerNorm critics, large batches and a behaviour-cloning penalty in
the critic's target as well as in the actor's loss, each with its own weight.

One call of :func:`update` is one gradient step on a mini-batch ``(s, a, r, s', d, a'_data)``,
``a'_data`` being the action the data took at ``s'``:

1. target action ``a' = clip(pi_targ(s') + clip(eps, -c, c), -max_a, max_a)``;
2. ``y = r + gamma (1 - d) (min_i Q_targ_i(s', a') - beta_2 sum_dims (a' - a'_data)^2)``, eq. (4);
3. critic loss ``sum_i mean_batch (Q_i(s, a) - y)^2``;
4. every ``policy_freq`` steps the actor minimises
   ``mean_batch (beta_1 sum_dims (pi(s) - a)^2 - lambda min_i Q_i(s, pi(s)))``, eq. (3), with
   ``lambda = 1 / mean_batch |min_i Q_i(s, pi(s))|`` (no gradient): TD3+BC's normalisation of Q,
   its alpha folded into beta_1, on the minimum of the critics where TD3+BC uses critic 1 only;
5. then the actor and critic targets move by Polyak averaging.

Sources: the paper's eqs. (3)-(4) and Tables 10-11; for what the paper leaves open (sums over
action dimensions, which Q lambda normalises, the order of the updates, the networks' details)
the authors' code, tinkoff-ai/ReBRAC's ``src/algorithms/rebrac.py`` and ``src/networks.py``, the
same as CORL's ``algorithms/offline/rebrac.py``. As they run it:

- the betas of Table 11 (``BC_WEIGHTS``), which for hopper-medium are also the authors' released
  ``configs/rebrac/hopper/hopper_medium.yaml`` (beta_2 0.001; CORL's config has 0.01);
- raw observations (``normalize_states: false`` in every config): the trainer's normaliser is the
  identity (the contract's ``normalize_observations``);
- each critic hidden layer is Dense, ReLU, then LayerNorm (Flax's, epsilon 1e-6); no LayerNorm in
  the actor (``actor_ln: false``);
- EDAC's initialisation: PyTorch's uniform weights, hidden biases 0.1, output layers uniform in
  +-1e-3 (actor) and +-3e-3 (critics);
- only the transitions whose next action the data has: a time-limit end, where the data has none,
  is left out (:func:`eabc.training.chunks.device_data`), as D4RL's ``qlearning_dataset`` does.

Where we still differ (docs/algorithms.md, "ReBRAC"):

- the smoothing noise and its clip scale with max_action, as in TD3+BC (the authors' assume 1,
  the D4RL tasks' max_action, where the two agree);
- the actor steps on gradient steps 2, 4, ... (the authors' on 1, 3, ...): the TD3 family's one
  schedule (TD3's and TD3+BC's code); the two orders give as many actor steps, each on critics
  one step apart, and a chunk's program stays the shared one.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp

from eabc import networks
from eabc.agents import td3_core
from eabc.agents.common import BatchWithNextActions
from eabc.agents.contract import CRITIC_METRICS, Algorithm
from eabc.data import tasks
from eabc.ranges import Count, Discount, Ensemble, Fraction, LearningRate, Settings, Weight, Widths


@dataclasses.dataclass(frozen=True)
class ReBRACConfig(Settings):
    """ReBRAC's settings: Table 10's for Gym-MuJoCo, the betas from Table 11 per dataset."""

    actor_bc_weight: Weight | None = None
    """beta_1 of eq. (3), the weight of sum_dims (pi(s) - a)^2 in the actor's loss; None: Table
    11's for the dataset."""
    critic_bc_weight: Weight | None = None
    """beta_2 of eq. (4), the weight of sum_dims (a' - a'_data)^2 in the critics' target; None:
    Table 11's for the dataset."""
    num_critics: Ensemble = 2
    """Critics; the target and the actor take their minimum."""
    discount: Discount = 0.99
    """gamma."""
    tau: Fraction = 0.005
    """Polyak rate of the target networks."""
    policy_noise: Weight = 0.2
    """Std of the target-policy smoothing noise, as a fraction of max_action."""
    noise_clip: Weight = 0.5
    """Clip of the smoothing noise, as a fraction of max_action."""
    policy_freq: Count = 2
    """The actor and the targets are updated every policy_freq critic steps."""
    actor_lr: LearningRate = 1e-3
    """Adam learning rate of the actor (Table 10: 1e-3 with batch 1024 on Gym-MuJoCo)."""
    critic_lr: LearningRate = 1e-3
    """Adam learning rate of the critics."""
    hidden_dims: Widths = (256, 256, 256)
    """Hidden layer widths of actor and critics (Table 10: 3 layers of 256)."""
    critic_layer_norm: bool = True
    """LayerNorm in every hidden layer of the critics (the paper's; the actor has none, as in
    the paper and in every config of the authors', actor_ln false)."""
    layer_norm_placement: Literal["after-relu", "before-relu"] = "after-relu"
    """Where each critic LayerNorm sits: after the hidden layer's ReLU (the authors' code, Flax's
    epsilon 1e-6) or before it (eabc-ln's and SEEM's, epsilon 1e-5)."""
    initialisation: Literal["edac", "pytorch"] = "edac"
    """edac: the authors' (EDAC's), hidden biases 0.1 and output layers uniform in +-1e-3 (actor)
    and +-3e-3 (critics); pytorch: PyTorch's default for every layer, as TD3+BC's."""
    normalize_q: bool = True
    """lambda = 1 / mean|Q| in the actor's loss (TD3+BC's normalisation); False: lambda = 1."""


PRESETS = {"rebrac": ReBRACConfig()}

# Table 11 of the paper: (beta_1 actor, beta_2 critic) per (environment, dataset kind). CORL's
# configs agree but for two critic weights, hopper-medium 0.001 (CORL 0.01) and hopper-expert
# 0.001 (CORL 0.1): we follow the paper, and for hopper-medium the authors' released config
# (tinkoff-ai/ReBRAC configs/rebrac/hopper/hopper_medium.yaml: 0.01, 0.001). Their repository's
# other Gym-MuJoCo configs, as stored, disagree with both the paper and CORL and hold learning
# rates no run of Table 10 used (walker2d_expert's critic 0.5, walker2d_random's actor 0.1), so
# they are not what the paper's results came from (docs/algorithms.md, "ReBRAC").
BC_WEIGHTS: dict[tuple[str, str], tuple[float, float]] = {
    ("halfcheetah", "random"): (0.001, 0.1),
    ("halfcheetah", "medium"): (0.001, 0.01),
    ("halfcheetah", "expert"): (0.01, 0.01),
    ("halfcheetah", "medium-expert"): (0.01, 0.1),
    ("halfcheetah", "medium-replay"): (0.01, 0.001),
    ("hopper", "random"): (0.001, 0.01),
    ("hopper", "medium"): (0.01, 0.001),
    ("hopper", "expert"): (0.1, 0.001),
    ("hopper", "medium-expert"): (0.1, 0.01),
    ("hopper", "medium-replay"): (0.05, 0.5),
    ("walker2d", "random"): (0.01, 0.0),
    ("walker2d", "medium"): (0.05, 0.1),
    ("walker2d", "expert"): (0.01, 0.5),
    ("walker2d", "medium-expert"): (0.01, 0.01),
    ("walker2d", "medium-replay"): (0.05, 0.01),
}


ReBRACState = td3_core.TD3State
"""TD3's networks, optimisers and step count: ReBRAC adds no state of its own."""


EDAC_INIT = {"hidden_bias": 0.1, "actor_output_bound": 1e-3, "critic_output_bound": 3e-3}
"""The authors' initialisation (EDAC's), beyond PyTorch's uniform weights: ``td3_core.init``'s."""


def init(key: jax.Array, obs_dim: int, act_dim: int, config: ReBRACConfig) -> ReBRACState:
    scheme = EDAC_INIT if config.initialisation == "edac" else {}
    return td3_core.init(key, obs_dim, act_dim, config, **scheme)


def _q(critic, obs, action, config: ReBRACConfig) -> jax.Array:
    """Every critic's Q: ``[K, B]``, its LayerNorms where ``layer_norm_placement`` puts them."""
    after_relu = config.layer_norm_placement == "after-relu"
    return networks.critic_apply(critic, obs, action, norm_after_relu=after_relu)


def _weights(config: ReBRACConfig) -> tuple[float, float]:
    if config.actor_bc_weight is None or config.critic_bc_weight is None:
        raise ValueError(
            "ReBRAC's betas are unset: resolve them from the dataset (Table 11, done by the "
            "trainer) or set actor_bc_weight and critic_bc_weight"
        )
    return config.actor_bc_weight, config.critic_bc_weight


def critic_loss(critic, critic_target, actor_target, batch: BatchWithNextActions, key, config,
                max_action):  # fmt: skip
    _, critic_bc_weight = _weights(config)
    next_action = td3_core.target_action(actor_target, batch, key, config, max_action)
    penalty = ((next_action - batch.next_actions) ** 2).sum(axis=-1)
    target_q = _q(critic_target, batch.next_observations, next_action, config)
    next_value = target_q.min(axis=0) - critic_bc_weight * penalty
    y = jax.lax.stop_gradient(batch.rewards + config.discount * (1.0 - batch.dones) * next_value)
    q = _q(critic, batch.observations, batch.actions, config)
    loss = ((q - y[None]) ** 2).mean(axis=1).sum()
    return loss, {
        "critic_loss": loss,
        "q_mean": q.mean(),
        "q_ensemble_std": q.std(axis=0, ddof=1).mean(),
        "target_mean": y.mean(),
        "critic_bc_penalty": penalty.mean(),
    }


def actor_loss(actor, critic, batch: BatchWithNextActions, config, max_action):
    actor_bc_weight, _ = _weights(config)
    pi = networks.actor_apply(actor, batch.observations, max_action)
    value = _q(critic, batch.observations, pi, config).min(axis=0)
    lam = jax.lax.stop_gradient(1.0 / jnp.abs(value).mean()) if config.normalize_q else 1.0
    bc = ((pi - batch.actions) ** 2).sum(axis=-1)
    loss = (actor_bc_weight * bc - lam * value).mean()
    return loss, {
        "actor_loss": loss,
        "actor_value": value.mean(),
        "lambda": jnp.asarray(lam, value.dtype),
        "bc_loss": bc.mean(),
    }


def update(
    state: ReBRACState,
    batch: BatchWithNextActions,
    key: jax.Array,
    config: ReBRACConfig,
    max_action: float,
    delayed: bool | None = None,
) -> tuple[ReBRACState, dict[str, jax.Array]]:
    """One gradient step ``t`` of ReBRAC; ``delayed``: whether ``t % policy_freq == 0`` (the
    actor's step), None: from ``state.step`` (see :func:`eabc.agents.td3_core.scheduled`). Pure:
    the same inputs always give the same outputs."""
    return td3_core.scheduled(_step, state, batch, key, config, max_action, delayed)


def _step(state, batch: BatchWithNextActions, key, config: ReBRACConfig, max_action, delayed):
    # Steps 1-3: the smoothed target action, eq. (4)'s penalised target, the critics' step.
    new, metrics = td3_core.critic_step(state, critic_loss, batch, key, config, max_action)
    if delayed:  # steps 4-5, eq. (3), on the critics just updated (as TD3+BC and CORL)
        new, actor_metrics = td3_core.actor_step(new, config, actor_loss, batch, config, max_action)
        metrics = {**metrics, **actor_metrics}
    return new, metrics


def resolve(config: ReBRACConfig, dataset_name: str, steps: int | None, given: frozenset[str]):
    """Table 11's betas for the dataset, where they are unset."""
    names = ("actor_bc_weight", "critic_bc_weight")
    unset = [name for name in names if getattr(config, name) is None]
    if not unset:
        return config
    betas = BC_WEIGHTS.get(tasks.parse_task(dataset_name))
    if betas is None:
        raise ValueError(
            f"no default ReBRAC betas for dataset {dataset_name!r} (Table 11 covers "
            "halfcheetah/hopper/walker2d x random/medium/expert/medium-expert/medium-replay); "
            "pass --set actor_bc_weight=B1 critic_bc_weight=B2"
        )
    return dataclasses.replace(config, **{n: b for n, b in zip(names, betas) if n in unset})


# steps/s (batch 1024, 3 x 256 networks, hopper shapes): EABC's 151 on the reference host over
# the ratio of the two timed on one core by benchmarks/algorithms.py (50.6 against 27.4 steps/s,
# docs/speed.md): 4 times the batch, one more hidden layer and the LayerNorms.
ALGORITHMS = (
    Algorithm("rebrac", "ReBRAC", PRESETS["rebrac"], init, update, resolve=resolve,
              delayed_period=td3_core.delayed_period,
              traced_settings=("actor_bc_weight", "critic_bc_weight"),
              batch_size=1024, next_actions=True, normalize_observations=False, column=12.5,
              step_metrics=CRITIC_METRICS | {"critic_bc_penalty"}, steps_per_s=82.0,
              state_layout=2),  # 2: raw observations, LayerNorm after the ReLU
)  # fmt: skip
