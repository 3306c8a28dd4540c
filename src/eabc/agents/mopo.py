"""MOPO (Yu et al., 2020): SAC on real data mixed with short rollouts of a learned dynamics ensemble
whose rewards are penalised by the ensemble's uncertainty; MOReL (:mod:`eabc.agents.morel`) is the
same loop with its halting rule instead of the penalty.

Before the policy loop, :func:`pretrain` fits the ensemble (:mod:`eabc.agents.dynamics`) on the
dataset; its parameters and elites live in the state, so checkpoints hold them and a resumed run
reuses them. One call of :func:`update` is then one SAC step:

1. every ``rollout_interval`` steps, ``h = rollout_length`` model steps from the batch's real
   states under the current policy go into a ring buffer held in the state: per step a random
   elite's Gaussian sample of ``(r, s' - s)``, the reward ``r - penalty_coeff * max_k |std_k|``
   (MOPO's ``penalty_learned_var``), ``d`` from the task's termination rule; a transition whose
   ensemble disagreement exceeds ``halt_threshold`` ends the rollout with ``halt_reward`` (MOReL;
   off for MOPO) and a terminated rollout writes nothing after its end;
2. the SAC batch is ``real_ratio`` real transitions and the rest uniform from the buffer;
3. SAC's update (:func:`eabc.agents.sac.update`) on that batch.

The official code rolls out 50,000 start states every 1,000 steps; refilling from the 256 states
of every 5th batch gives the same ~50 rollouts per gradient step.

Why one file of about 340 lines: a third of it is the settings, with the official configs' per-task
rollout length and penalty for all twelve MuJoCo tasks; the rest is the one loop MOReL shares.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Annotated, Any, ClassVar, Literal

import annotated_types
import jax
import jax.numpy as jnp

from eabc import pytree
from eabc.agents import dynamics, sac
from eabc.agents.common import Batch, BuiltOn
from eabc.agents.contract import Algorithm
from eabc.data import tasks
from eabc.ranges import (
    Count,
    Discount,
    Finite,
    Fraction,
    LearningRate,
    NonNegativeCount,
    Settings,
    Weight,
    Widths,
)

"""The actor outputs a tanh-Gaussian; its deterministic action is ``tanh(mean)``."""


@dataclasses.dataclass(frozen=True)
class MOPOConfig(Settings):
    """MOPO's settings: the official configs (tianheyu927/mopo, ``examples/config/d4rl/``:
    ``base.py``, ``base_mopo.py`` and one file per task) and its model (``mopo/models``)."""

    rollout_length: Count = 5
    """h, model steps per rollout; per task from the official configs (:data:`TASK_SETTINGS`)."""
    penalty_coeff: Weight = 1.0
    """lambda of ``r - lambda u(s, a)``; per task from the official configs."""
    real_ratio: Annotated[float, annotated_types.Interval(ge=0, lt=1)] = 0.05
    """Share of real transitions in every SAC batch (base.py)."""
    rollout_interval: Count = 5
    """Refill the model buffer every this many steps (see the module docstring)."""
    buffer_capacity: Count = 200_000
    """Transitions the model buffer keeps (the official keeps 5 epochs of rollouts, 1.25M at h = 5;
    200K keeps checkpoints near 20 MB)."""
    termination: Literal["auto", "hopper", "walker2d", "none"] = "auto"
    """Termination rule of model rollouts: hopper, walker2d, none, or auto (from the dataset)."""
    halt_threshold: Weight | None = None
    """MOReL's: disagreement beyond which a rollout halts (None: never, MOPO)."""
    halt_reward: Finite = 0.0
    """MOReL's reward of the halting transition."""
    model_members: Count = 7
    """Dynamics ensemble size (base.py num_networks)."""
    model_elites: Count = 5
    """Elites that roll out (base.py num_elites)."""
    model_hidden_dims: Widths = (200, 200, 200, 200)
    """Dynamics MLP widths (constructor.py)."""
    model_activation: dynamics.Activation = "swish"
    """Dynamics activation (constructor.py)."""
    model_sample: bool = True
    """Sample the elite's Gaussian (base.py deterministic=False); False: its mean."""
    model_max_epochs: Count | None = None
    """Cap on model epochs (official: none, early stopping only)."""
    model_patience: NonNegativeCount = 5
    """Model early-stopping patience in epochs (bnn.py max_epochs_since_update)."""
    num_critics: Count = 2
    """SAC's Q-networks (softlearning)."""
    discount: Discount = 0.99
    """gamma (base.py)."""
    tau: Fraction = 5e-3
    """Polyak rate (base.py)."""
    actor_lr: LearningRate = 3e-4
    """SAC's Adam rates (softlearning's default)."""
    critic_lr: LearningRate = 3e-4
    """SAC's critic Adam rate (softlearning)."""
    alpha_lr: LearningRate = 3e-4
    """SAC's temperature Adam rate (softlearning)."""
    target_entropy: Finite | None = -3.0
    """SAC's entropy target (base.py: -3 for every task); None: -act_dim."""
    hidden_dims: Widths = (256, 256)
    """Actor and critic widths (softlearning's 256-256)."""

    def __post_init__(self):
        super().__post_init__()
        if self.model_elites > self.model_members:
            raise ValueError(
                f"model_elites must be at most model_members={self.model_members}, got "
                f"{self.model_elites}: the elites are members of the ensemble"
            )

    @property
    def model(self) -> dynamics.DynamicsConfig:
        return dynamics.DynamicsConfig(
            num_members=self.model_members,
            num_elites=self.model_elites,
            hidden_dims=self.model_hidden_dims,
            activation=self.model_activation,
            max_epochs=self.model_max_epochs,
            patience=self.model_patience,
        )

    @property
    def sac(self) -> sac.SACConfig:
        return sac.SACConfig(
            num_critics=self.num_critics,
            discount=self.discount,
            tau=self.tau,
            actor_lr=self.actor_lr,
            critic_lr=self.critic_lr,
            alpha_lr=self.alpha_lr,
            target_entropy=self.target_entropy,
            hidden_dims=self.hidden_dims,
        )


PRESETS: dict[str, MOPOConfig] = {"mopo": MOPOConfig()}

TASK_SETTINGS: dict[tuple[str, str], dict[str, float]] = {
    # examples/config/d4rl/<env>_<kind>.py of tianheyu927/mopo: rollout_length and penalty_coeff
    # ("mixed" is D4RL's medium-replay). All twelve as in the files at commit 3d632fc (note
    # halfcheetah-medium-expert's penalty, 5.0).
    ("halfcheetah", "random"): {"rollout_length": 5, "penalty_coeff": 0.5},
    ("halfcheetah", "medium"): {"rollout_length": 1, "penalty_coeff": 1.0},
    ("halfcheetah", "medium-replay"): {"rollout_length": 5, "penalty_coeff": 1.0},
    ("halfcheetah", "medium-expert"): {"rollout_length": 5, "penalty_coeff": 5.0},
    ("hopper", "random"): {"rollout_length": 5, "penalty_coeff": 1.0},
    ("hopper", "medium"): {"rollout_length": 5, "penalty_coeff": 5.0},
    ("hopper", "medium-replay"): {"rollout_length": 5, "penalty_coeff": 1.0},
    ("hopper", "medium-expert"): {"rollout_length": 5, "penalty_coeff": 1.0},
    ("walker2d", "random"): {"rollout_length": 1, "penalty_coeff": 1.0},
    ("walker2d", "medium"): {"rollout_length": 5, "penalty_coeff": 5.0},
    ("walker2d", "medium-replay"): {"rollout_length": 1, "penalty_coeff": 1.0},
    ("walker2d", "medium-expert"): {"rollout_length": 1, "penalty_coeff": 2.0},
}
"""MOPO's per-task rollout length h and penalty lambda (the paper has no expert setting)."""


def resolve(config: MOPOConfig, dataset_name: str, steps: int, given: frozenset[str]) -> MOPOConfig:
    """The per-task settings for ``dataset_name`` where the user did not set them; the
    termination rule from its environment. Called by the trainer."""
    task = tasks.parse_task(dataset_name)
    updates: dict[str, Any] = {}
    if task is not None:
        updates |= {k: v for k, v in TASK_SETTINGS.get(task, {}).items() if k not in given}
    if config.termination == "auto":
        env = task[0] if task is not None else None
        updates["termination"] = env if env in ("hopper", "walker2d") else "none"
    return dataclasses.replace(config, **updates)


@pytree.dataclass
class MOPOState(BuiltOn):
    BASE: ClassVar[str] = "sac"

    sac: sac.SACState
    """SAC's actor, critics, target critics, temperature and optimisers."""
    model: dynamics.Params
    """The dynamics ensemble (trained by :func:`pretrain`)."""
    elites: jax.Array
    """Indices of the elite members."""
    halt_threshold: jax.Array
    """Disagreement beyond which a rollout halts (inf: never)."""
    obs_mean: jax.Array
    """The trainer's observation normaliser, for the termination rule on raw observations."""
    obs_std: jax.Array
    buffer: Batch
    """The model-rollout ring buffer, ``[capacity, ...]``."""
    buffer_ptr: jax.Array
    buffer_count: jax.Array
    rollout_metrics: dict[str, jax.Array]
    """The latest refill's metrics (:func:`rollout`), which every step reports: a chunk's log
    row then shows their real values, not a fifth of them."""


ROLLOUT_METRICS = ("rollout_penalty", "rollout_disagreement", "rollout_done")
"""What a refill measures over the transitions it writes: the mean penalty ``u(s, a)``, the mean
disagreement, the share of ended rollouts."""


def init(key: jax.Array, obs_dim: int, act_dim: int, config: MOPOConfig) -> MOPOState:
    sac_key, model_key = jax.random.split(key)
    capacity = config.buffer_capacity
    threshold = jnp.inf if config.halt_threshold is None else config.halt_threshold
    return MOPOState(
        sac=sac.init(sac_key, obs_dim, act_dim, config.sac),
        model=dynamics.init(model_key, obs_dim, act_dim, config.model),
        elites=jnp.arange(config.model_elites, dtype=jnp.int32),
        halt_threshold=jnp.asarray(threshold, jnp.float32),
        obs_mean=jnp.zeros(obs_dim),
        obs_std=jnp.ones(obs_dim),
        buffer=Batch(
            observations=jnp.zeros((capacity, obs_dim)),
            actions=jnp.zeros((capacity, act_dim)),
            rewards=jnp.zeros(capacity),
            next_observations=jnp.zeros((capacity, obs_dim)),
            dones=jnp.zeros(capacity),
        ),
        buffer_ptr=jnp.zeros((), jnp.int32),
        buffer_count=jnp.zeros((), jnp.int32),
        rollout_metrics={name: jnp.zeros(()) for name in ROLLOUT_METRICS},
    )


def pretrain(
    state: MOPOState, data: Batch, key: jax.Array, config: MOPOConfig, normalizer, progress=None
):
    """Fit the dynamics ensemble to the (normalised) dataset once, before the policy loop
    (continuing the fit that ``progress`` holds, if any)."""
    model, elites, info = dynamics.fit(key, data, config.model, log=_log, progress=progress)
    _log(
        f"dynamics: {info['model_epochs']} epochs, elites' held-out error "
        f"{info['model_heldout_error']:.4f} (variance-normalised; predicting the mean: 1), MSE "
        f"{info['model_heldout_mse']:.4f} (predicting the mean: {info['model_heldout_mse_of_mean']:.4f})"
    )
    return state.replace(
        model=model,
        elites=elites,
        obs_mean=jnp.asarray(normalizer.mean),
        obs_std=jnp.asarray(normalizer.std),
    )


def _log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def terminated(raw_next_obs: jax.Array, rule: str) -> jax.Array:
    """MBPO/MOPO's static termination rules (``static_fns``) on raw observations."""
    if rule == "hopper":
        height, angle = raw_next_obs[:, 0], raw_next_obs[:, 1]
        healthy = (
            jnp.isfinite(raw_next_obs).all(-1)
            & (jnp.abs(raw_next_obs[:, 1:]) < 100).all(-1)
            & (height > 0.7)
            & (jnp.abs(angle) < 0.2)
        )
        return ~healthy
    if rule == "walker2d":
        height, angle = raw_next_obs[:, 0], raw_next_obs[:, 1]
        healthy = (height > 0.8) & (height < 2.0) & (angle > -1.0) & (angle < 1.0)
        return ~healthy
    return jnp.zeros(raw_next_obs.shape[0], bool)


def model_step(state: MOPOState, obs, actions, key, config: MOPOConfig):
    """One step of the pessimistic model: ``(s', r~, done, penalty, disagreement)``."""
    member_key, noise_key = jax.random.split(key)
    mean, logvar = dynamics.predict(state.model, obs, actions, config.model_activation)
    size = obs.shape[0]
    members = state.elites[jax.random.randint(member_key, (size,), 0, state.elites.shape[0])]
    pick = mean[members, jnp.arange(size)]
    if config.model_sample:
        std = jnp.exp(0.5 * logvar[members, jnp.arange(size)])
        pick = pick + std * jax.random.normal(noise_key, pick.shape)
    next_obs = obs + pick[:, 1:]
    penalty = dynamics.max_std_norm(logvar)
    spread = dynamics.disagreement(mean[..., 1:])
    halted = spread > state.halt_threshold
    reward = pick[:, 0] - config.penalty_coeff * penalty
    reward = jnp.where(halted, config.halt_reward, reward)
    raw = next_obs * state.obs_std + state.obs_mean
    done = terminated(raw, config.termination) | halted
    return next_obs, reward, done, penalty, spread


def rollout(state: MOPOState, start_obs, key, config: MOPOConfig, max_action: float):
    """``h`` model steps from ``start_obs`` written into the ring buffer (ended rollouts stop)."""

    def one(carry, key):
        obs, alive = carry
        action_key, model_key = jax.random.split(key)
        action, _ = sac.sample_action(state.actor, obs, action_key, max_action)
        next_obs, reward, done, penalty, spread = model_step(state, obs, action, model_key, config)
        step = Batch(obs, action, reward, next_obs, done.astype(jnp.float32))
        return (next_obs, alive & ~done), (step, alive, penalty, spread, done)

    alive = jnp.ones(start_obs.shape[0], bool)
    keys = jax.random.split(key, config.rollout_length)
    _, (steps, written, penalty, spread, done) = jax.lax.scan(one, (start_obs, alive), keys)
    flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), steps)
    written = written.reshape(-1)
    capacity = config.buffer_capacity
    position = (state.buffer_ptr + jnp.cumsum(written) - 1) % capacity
    position = jnp.where(written, position, capacity)  # out of range: dropped
    buffer = jax.tree.map(lambda b, x: b.at[position].set(x, mode="drop"), state.buffer, flat)
    count = written.sum()
    per = jnp.maximum(count, 1)
    new_state = state.replace(
        buffer=buffer,
        buffer_ptr=(state.buffer_ptr + count) % capacity,
        buffer_count=jnp.minimum(state.buffer_count + count, capacity),
    )
    return new_state, {
        "rollout_penalty": (penalty.reshape(-1) * written).sum() / per,
        "rollout_disagreement": (spread.reshape(-1) * written).sum() / per,
        "rollout_done": (done.reshape(-1) * written).sum() / per,
    }


def mixed_batch(state: MOPOState, batch: Batch, key, config: MOPOConfig) -> Batch:
    """``real_ratio`` of ``batch`` (its first rows) and the rest uniform from the model buffer."""
    size = batch.rewards.shape[0]
    num_real = int(round(config.real_ratio * size))
    index = jax.random.randint(key, (size - num_real,), 0, jnp.maximum(state.buffer_count, 1))
    model = jax.tree.map(lambda x: x[index], state.buffer)
    return jax.tree.map(lambda r, m: jnp.concatenate([r[:num_real], m]), batch, model)


def update(
    state: MOPOState, batch: Batch, key: jax.Array, config: MOPOConfig, max_action: float
) -> tuple[MOPOState, dict[str, jax.Array]]:
    """Refill the model buffer when due, then one SAC step on the mixed batch. Pure. Every step
    reports the latest refill's metrics."""
    rollout_key, sample_key, sac_key = jax.random.split(key, 3)

    def refill(state: MOPOState) -> MOPOState:
        state, rollout_metrics = rollout(state, batch.observations, rollout_key, config, max_action)
        return state.replace(rollout_metrics=rollout_metrics)

    state = jax.lax.cond(state.step % config.rollout_interval == 0, refill, lambda s: s, state)
    mixed = mixed_batch(state, batch, sample_key, config)
    base, metrics = sac.update(state.sac, mixed, sac_key, config.sac, max_action)
    state = state.replace(sac=base)
    return state, {**metrics, **state.rollout_metrics, "model_buffer": state.buffer_count}


HALTS = frozenset({"halt_threshold"})
"""The state's entries that may hold +-inf: the halting threshold, inf where rollouts never halt."""


def _fit_seconds(config: MOPOConfig) -> float:
    return dynamics.fit_seconds(config.model)


ALGORITHMS = (
    # steps/s: the reference host's (eabc.timing), by benchmarks/algorithms.py, without the fit.
    # state_layout 2: the SAC state as one field
    Algorithm("mopo", "MOPO", PRESETS["mopo"], init, update, column=9, actor="tanh-gaussian",
              pretrain=pretrain, pretrain_s=_fit_seconds, resolve=resolve, steps_per_s=168.0, state_layout=2,
              infinite_state=HALTS),
)  # fmt: skip
