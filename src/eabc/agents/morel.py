"""MOReL (Kidambi, Rajeswaran, Netrapalli & Joachims, 2020): a policy optimised inside the
pessimistic MDP of a learned dynamics ensemble, which halts (an absorbing end with
``halt_reward``) wherever the members disagree beyond a threshold.

As in the official code (aravindr93/mjrl, ``projects/morel/run_morel.py`` with
``configs/d4rl_hopper_medium.txt``), the disagreement of ``(s, a)`` is the largest distance between
two members' predicted next states, and the threshold is ``pessimism_coef`` times its maximum over
the dataset, computed once after the model is fitted (:func:`pretrain`).

The planner is not the paper's. The official code optimises a 64-64 Gaussian policy by natural
policy gradient on 50 model rollouts of horizon 700 per iteration; this package's training loop is
one pure per-step update inside ``lax.scan``, so MOReL here runs the SAC loop of
:mod:`eabc.agents.mopo` (short branched rollouts from dataset states, mixed with real data) inside
the same pessimistic MDP: MOPO and MOReL then differ only in their pessimism, the reward penalty
versus halting.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from eabc.agents import dynamics, mopo
from eabc.agents.common import Batch
from eabc.agents.contract import Algorithm
from eabc.agents.mopo import MOPOState, init, update  # noqa: F401  (the contract: init, update)
from eabc.ranges import Count, Finite, Weight, Widths

"""The actor outputs a tanh-Gaussian; its deterministic action is ``tanh(mean)``."""


@dataclasses.dataclass(frozen=True)
class MOReLConfig(mopo.MOPOConfig):
    """MOReL's settings: the official hopper-medium config where they apply; the SAC loop's from
    :class:`eabc.agents.mopo.MOPOConfig`."""

    pessimism_coef: Weight = 3.0
    """Threshold = this x the dataset's maximum disagreement (config pessimism_coef)."""
    halt_reward: Finite = 0.0
    """Reward of the halting step (config truncate_reward = 0 for D4RL hopper-medium; the paper
    writes -kappa, a negative constant)."""
    penalty_coeff: Weight = 0.0
    """No reward penalty: MOReL's pessimism is the halting alone."""
    model_members: Count = 4
    """Ensemble size (config num_models)."""
    model_elites: Count = 4
    """Every member rolls out (the official picks one of the 4 models at random)."""
    model_hidden_dims: Widths = (512, 512)
    """Dynamics widths (config hidden_size)."""
    model_activation: dynamics.Activation = "relu"
    """Dynamics activation (config activation)."""
    model_sample: bool = False
    """The official models are deterministic: roll out a member's mean."""
    model_max_epochs: Count | None = 25
    """Dynamics epochs (config fit_epochs)."""


PRESETS: dict[str, MOReLConfig] = {"morel": MOReLConfig()}


def resolve(
    config: MOReLConfig, dataset_name: str, steps: int, given: frozenset[str]
) -> MOReLConfig:
    """The termination rule from the dataset's environment (MOPO's per-task h and lambda do not
    apply: MOReL's official config is one for all tasks)."""
    keep = given | {"rollout_length", "penalty_coeff"}
    return mopo.resolve(config, dataset_name, steps, keep)


def dataset_disagreement(model, data: Batch, activation: str, chunk: int = 8192) -> jax.Array:
    """The disagreement of every dataset transition, ``[N]``, in chunks."""
    size = data.rewards.shape[0]
    pad = (-size) % chunk
    obs = jnp.pad(data.observations, ((0, pad), (0, 0))).reshape(
        -1, chunk, data.observations.shape[1]
    )
    act = jnp.pad(data.actions, ((0, pad), (0, 0))).reshape(-1, chunk, data.actions.shape[1])

    def one(xs):
        mean, _ = dynamics.predict(model, xs[0], xs[1], activation)
        return dynamics.disagreement(mean[..., 1:])

    return jax.lax.map(jax.jit(one), (obs, act)).reshape(-1)[:size]


def pretrain(
    state: MOPOState, data: Batch, key: jax.Array, config: MOReLConfig, normalizer, progress=None
):
    """Fit the ensemble (MOPO's :func:`eabc.agents.mopo.pretrain`), then set the threshold."""
    state = mopo.pretrain(state, data, key, config, normalizer, progress)
    spread = dataset_disagreement(state.model, data, config.model_activation)
    threshold = config.pessimism_coef * spread.max()
    mopo._log(f"MOReL: halting threshold {float(threshold):.4f} ({config.pessimism_coef} x max)")
    return state.replace(halt_threshold=jnp.asarray(threshold, jnp.float32))


_fit_seconds = mopo._fit_seconds

ALGORITHMS = (
    # steps/s: the reference host's (eabc.timing), by benchmarks/algorithms.py, without the fit.
    # state_layout 2: MOPO's state, which holds the SAC state as one field
    Algorithm("morel", "MOReL", PRESETS["morel"], init, update, column=8, actor="tanh-gaussian",
              pretrain=pretrain, pretrain_s=_fit_seconds, resolve=resolve, steps_per_s=192.0, state_layout=2,
              infinite_state=mopo.HALTS),
)  # fmt: skip
