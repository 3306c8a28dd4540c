"""A learned dynamics model: an ensemble of probabilistic MLPs, the shared model of MOPO and MOReL.

Member ``k`` maps ``(s, a)`` to a diagonal Gaussian over ``(r, s' - s)``: ``mean_k`` and
``logvar_k``, the log-variance softly bounded by learned ``max_logvar`` / ``min_logvar`` (shared by
the members). As in the MBPO/MOPO model (``mbpo/models/bnn.py``, which MOPO uses unchanged):

- training loss ``sum_k mean (mean_k - y)^2 exp(-logvar_k) + mean logvar_k``, plus L2 weight decay
  per layer and ``0.01 (sum max_logvar - sum min_logvar)``;
- every member trains on its own bootstrap resample of the training split, reshuffled per epoch;
- a held-out split (``holdout_ratio`` of the data, at most ``max_holdout`` transitions) scores
  every member after each epoch; training stops once no member has improved by more than 1% for
  ``patience`` epochs, each member keeps its best snapshot, and the ``num_elites`` best members
  by held-out error are the elites.

The held-out score is not bnn.py's. bnn.py scores a member by its plain mean squared error over
all outputs (``mse_loss``), so the output with the largest spread decides: on the tests' Pendulum
data the reward (variance 6.0 against 0.013-0.038 for the normalised state changes) stopped a
64-64 model after 11 epochs (its best at epoch 4) while its training NLL kept falling; scored as
here, it trained 74 epochs and its next-state errors came out 50-100 times smaller (the reward's
2.4 times). Here the score is :func:`heldout_error`: each output's squared error divided by that
output's variance over the held-out split, averaged over outputs, so that every output counts
alike (1 is what predicting the mean scores). Where the outputs' spreads are alike it ranks members as bnn.py's does. Not
the held-out Gaussian NLL: it can be negative and has no scale, so bnn.py's relative 1% rule
would not apply, and its ``log var`` terms reward the outputs with the smallest noise most.

Members are one vectorised network (weights ``[K, in, out]``) like the critic ensembles.
Observations arrive already normalised by the trainer; actions lie in the action box.

A fit on 1M transitions takes most of an hour on one core, so :func:`fit` can keep its state
after every epoch (``progress``) and continue from it: each epoch's shuffle depends only on the
key and the epoch's number, so a fit killed and continued ends with the same members, bit for bit,
as one that ran through.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable
from typing import Annotated, Literal

import annotated_types
import jax
import jax.numpy as jnp
import numpy as np
import optax

from eabc import networks, programs, pytree
from eabc.agents.common import Batch, apply_gradients
from eabc.agents.contract import PretrainProgress
from eabc.ranges import Count, LearningRate, NonNegativeCount, Settings, Weight, Widths

Params = dict


Activation = Literal["swish", "relu"]
Decays = Annotated[tuple[Weight, ...], annotated_types.MinLen(1)]
"""L2 weights, one or more finite numbers >= 0."""


@dataclasses.dataclass(frozen=True)
class DynamicsConfig(Settings):
    """The ensemble's settings; defaults are MOPO's (``mopo/models/constructor.py``, ``bnn.py``)."""

    num_members: Count = 7
    """Ensemble size (MOPO's num_networks)."""
    num_elites: Count = 5
    """Members kept for rollouts (MOPO's num_elites)."""
    hidden_dims: Widths = (200, 200, 200, 200)
    """Hidden widths (MOPO: four layers of 200)."""
    activation: Activation = "swish"
    """Hidden activation, swish or relu (MOPO: swish)."""
    weight_decays: Decays = (2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4)
    """L2 weight per layer, input to output (MOPO's FC weight_decay); shorter: the last repeats."""
    lr: LearningRate = 1e-3
    """Adam learning rate (MOPO)."""
    batch_size: Count = 256
    """Mini-batch per member (MOPO's _train_model)."""
    holdout_ratio: Annotated[float, annotated_types.Interval(gt=0, lt=1)] = 0.2
    """Share of the data held out (MOPO's _train_model)."""
    max_holdout: Count = 5000
    """At most this many held-out transitions (bnn.py's max_logging)."""
    patience: NonNegativeCount = 5
    """Epochs without a 1% improvement of any member before stopping (max_epochs_since_update)."""
    max_epochs: Count | None = None
    """Cap on epochs (MOPO: None, train until the patience runs out)."""

    def __post_init__(self):
        super().__post_init__()
        if self.num_elites > self.num_members:
            raise ValueError(
                f"num_elites must be at most num_members={self.num_members}, got "
                f"{self.num_elites}: the elites are members of the ensemble"
            )


INIT_MAX_LOGVAR, INIT_MIN_LOGVAR = 0.5, -10.0
"""bnn.py's initial log-variance bounds."""
LOGVAR_BOUND_WEIGHT = 0.01
"""bnn.py's weight of ``sum max_logvar - sum min_logvar``."""
IMPROVEMENT = 0.01
"""A member improves when its held-out error falls by more than 1% (bnn.py's _save_best)."""


def init(key: jax.Array, obs_dim: int, act_dim: int, config: DynamicsConfig) -> Params:
    out = obs_dim + 1
    return {
        "net": networks.init_mlp(
            key, (obs_dim + act_dim, *config.hidden_dims, 2 * out), num_members=config.num_members
        ),
        # float32, not weakly typed: the first epoch's inputs then have the types of every later
        # epoch's, and _epoch compiles once per fit instead of three times.
        "max_logvar": jnp.full((out,), INIT_MAX_LOGVAR, jnp.float32),
        "min_logvar": jnp.full((out,), INIT_MIN_LOGVAR, jnp.float32),
    }


def predict(params: Params, obs, actions, activation: str = "swish"):
    """``(mean, logvar)`` of ``(r, s' - s)`` for every member, ``[K, B, 1 + obs_dim]``.

    ``obs, actions`` are ``[B, .]`` (every member sees them) or ``[K, B, .]`` (one batch each).
    """
    act = jax.nn.swish if activation == "swish" else jax.nn.relu
    net = params["net"]
    n = networks.num_layers(net)
    h = jnp.concatenate([obs, actions], axis=-1)
    pattern = "kbi,kio->kbo" if h.ndim == 3 else "bi,kio->kbo"
    h = jnp.einsum(pattern, h, net["w0"]) + net["b0"][:, None, :]
    for layer in range(1, n):
        h = jnp.einsum("kbi,kio->kbo", act(h), net[f"w{layer}"]) + net[f"b{layer}"][:, None, :]
    mean, logvar = jnp.split(h, 2, axis=-1)
    max_logvar, min_logvar = params["max_logvar"], params["min_logvar"]
    logvar = max_logvar - jax.nn.softplus(max_logvar - logvar)
    logvar = min_logvar + jax.nn.softplus(logvar - min_logvar)
    return mean, logvar


def targets(batch: Batch) -> jax.Array:
    """What the model predicts: ``(r, s' - s)``."""
    return jnp.concatenate(
        [batch.rewards[..., None], batch.next_observations - batch.observations], axis=-1
    )


def training_loss(params: Params, obs, actions, y, config: DynamicsConfig) -> jax.Array:
    """Gaussian NLL summed over members (inputs ``[K, B, .]``), weight decay, log-variance bounds."""
    mean, logvar = predict(params, obs, actions, config.activation)
    nll = (((mean - y) ** 2) * jnp.exp(-logvar)).mean(axis=(1, 2)) + logvar.mean(axis=(1, 2))
    n = networks.num_layers(params["net"])
    decays = [config.weight_decays[min(i, len(config.weight_decays) - 1)] for i in range(n)]
    decay = sum(d * 0.5 * (params["net"][f"w{i}"] ** 2).sum() for i, d in enumerate(decays))
    bounds = LOGVAR_BOUND_WEIGHT * (params["max_logvar"].sum() - params["min_logvar"].sum())
    return nll.sum() + decay + bounds


def heldout_error(
    params: Params, obs, actions, y, activation: str = "swish", variance: jax.Array | None = None
) -> jax.Array:
    """Every member's mean over outputs of its mean prediction's squared error divided by the
    output's ``variance`` (``[1 + obs_dim]``; None: 1, the plain mean squared error), ``[K]``."""
    mean, _ = predict(params, obs, actions, activation)
    error = (mean - y[None]) ** 2
    if variance is not None:
        error = error / variance
    return error.mean(axis=(1, 2))


_heldout_error = jax.jit(heldout_error, static_argnames="activation")


MIN_VARIANCE = 1e-8
"""Floor of an output's held-out variance in :func:`heldout_error` (a constant output)."""


def _prepare(key: jax.Array, data: Batch, config: DynamicsConfig) -> dict:
    """What a fit draws and computes before its first epoch: the held-out split, the members'
    bootstrap samples of the training split, the targets, the initial ensemble and optimiser.
    One program, built as those that run once are (:data:`eabc.networks.INIT_COMPILE_OPTIONS`);
    drawn op by op, each operation compiled a program of its own, some 90 per fit."""
    size = data.rewards.shape[0]
    obs_dim, act_dim = data.observations.shape[1], data.actions.shape[1]
    split_key, init_key, boot_key, epoch_key = jax.random.split(key, 4)
    permutation = jax.random.permutation(split_key, size)
    num_holdout = min(int(size * config.holdout_ratio), config.max_holdout)
    holdout, train = permutation[:num_holdout], permutation[num_holdout:]
    y = targets(data)
    y_held = y[holdout]
    shape = (config.num_members, train.shape[0])
    params = init(init_key, obs_dim, act_dim, config)
    return {
        "epoch_key": epoch_key,
        "held": jax.tree.map(lambda x: x[holdout], data),
        "y": y,
        "y_held": y_held,
        "bootstrap": train[jax.random.randint(boot_key, shape, 0, train.shape[0])],
        "params": params,
        "opt_state": optax.adam(config.lr).init(params),
        "variance": jnp.maximum(y_held.var(axis=0), MIN_VARIANCE),
        "baseline": ((y_held - y[train].mean(axis=0)) ** 2).mean(),
    }


_prepare_compiled = programs.Program(
    _prepare, networks.INIT_COMPILE_OPTIONS, static_argnames=("config",)
)


@functools.partial(jax.jit, static_argnames=("config",))
def _epoch(params, opt_state, epoch_key, epoch, bootstrap, data: Batch, y, config: DynamicsConfig):
    """One pass over the training split, in an order of its own for every member (drawn from
    ``epoch_key`` and ``epoch``) through the member's bootstrap sample."""
    k, steps = config.num_members, max(bootstrap.shape[1] // config.batch_size, 1)
    keys = jax.random.split(jax.random.fold_in(epoch_key, epoch), k)
    shuffle = jax.vmap(jax.random.permutation)(keys, bootstrap)
    order = shuffle[:, : steps * config.batch_size].reshape(k, steps, config.batch_size)
    tx = optax.adam(config.lr)

    def step(carry, index):
        params, opt_state = carry
        loss, grads = jax.value_and_grad(training_loss)(
            params, data.observations[index], data.actions[index], y[index], config
        )
        return apply_gradients(tx, grads, opt_state, params), loss

    (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), order.transpose(1, 0, 2))
    return params, opt_state, losses.mean()


def fit(
    key: jax.Array,
    data: Batch,
    config: DynamicsConfig,
    log: Callable[[str], None] | None = None,
    progress: PretrainProgress | None = None,
) -> tuple[Params, jax.Array, dict[str, float]]:
    """Train an ensemble on ``data`` (one device-resident batch of all transitions).

    Returns the best snapshot of every member, the elites' indices (best first) and a summary.
    Deterministic given ``key``. With ``progress`` the fit saves its state after every epoch and
    starts from what ``progress`` holds when that is a fit of the same key, data size and
    settings (the stopping rule, ``max_epochs`` and ``patience``, may differ).
    """
    size = data.rewards.shape[0]
    obs_dim, act_dim = data.observations.shape[1], data.actions.shape[1]
    start = _prepare_compiled(key, data, config)
    held, y, y_held = start["held"], start["y"], start["y_held"]
    params, opt_state = start["params"], start["opt_state"]
    error = functools.partial(
        _heldout_error, activation=config.activation, variance=start["variance"]
    )
    best = np.asarray(error(params, held.observations, held.actions, y_held))
    best_params, since, epoch, losses = params, 0, 0, []
    signature = _signature(key, size, obs_dim, act_dim, config)
    saved = progress.load() if progress is not None else None
    if saved is not None and saved.get("signature") == signature:
        template = {"params": params, "opt_state": opt_state, "best_params": best_params}
        restored = pytree.from_state_dict(template, saved)
        params, opt_state = restored["params"], restored["opt_state"]
        best_params = restored["best_params"]
        best, losses = np.asarray(saved["best"]), [float(x) for x in saved["losses"]]
        since, epoch = int(saved["since"]), int(saved["epoch"])
        if log is not None:
            log(f"dynamics: continuing the fit after epoch {epoch} (saved by a run that stopped)")
    elif saved is not None and log is not None:
        log("dynamics: the saved fit is of other settings or data; fitting from the start")
    while since <= config.patience and (config.max_epochs is None or epoch < config.max_epochs):
        params, opt_state, loss = _epoch(
            params, opt_state, start["epoch_key"], epoch, start["bootstrap"], data, y, config
        )
        current = np.asarray(error(params, held.observations, held.actions, y_held))
        improved = (best - current) / np.maximum(best, 1e-12) > IMPROVEMENT
        best = np.where(improved, current, best)
        best_params = _select_members(jnp.asarray(improved), params, best_params)
        since = 0 if improved.any() else since + 1
        epoch += 1
        losses.append(float(loss))
        if progress is not None:
            progress.save({
                "signature": signature, "epoch": epoch, "since": since, "best": best,
                "losses": np.asarray(losses), "params": params, "opt_state": opt_state,
                "best_params": best_params,
            })  # fmt: skip
        if log is not None:
            log(f"dynamics epoch {epoch}: train loss {loss:.4f}, held-out error {np.sort(current)}")
    final = np.asarray(error(best_params, held.observations, held.actions, y_held))
    elites = jnp.asarray(np.argsort(final)[: config.num_elites], jnp.int32)
    mse = _heldout_error(best_params, held.observations, held.actions, y_held, config.activation)
    baseline = float(start["baseline"])
    info = {
        "model_epochs": epoch,
        "model_heldout_error": float(final[np.asarray(elites)].mean()),
        "model_heldout_mse": float(np.asarray(mse)[np.asarray(elites)].mean()),
        "model_heldout_mse_of_mean": baseline,
        "model_train_loss": losses[-1] if losses else float("nan"),
    }
    return best_params, elites, info


def _signature(key, size: int, obs_dim: int, act_dim: int, config: DynamicsConfig) -> str:
    """What decides a fit's every epoch: a saved fit with another signature is not continued."""
    settings = dataclasses.asdict(config)
    for name in ("max_epochs", "patience"):  # when to stop, not what an epoch does
        settings.pop(name)
    return json.dumps(
        {"key": np.asarray(jax.random.key_data(key)).tolist(), "size": size, "obs_dim": obs_dim, "act_dim": act_dim,
         "settings": settings}, sort_keys=True,
    )  # fmt: skip


FIT_FLOPS_PER_S = 1.0e11
"""Training throughput of :func:`fit` (2 flops per multiply-add, forward and backward) on one
core of the reference host (:data:`eabc.timing.REFERENCE_HOST`), for the cost hint of
:func:`fit_seconds`: MOPO's fit on hopper-medium ran 35 epochs in about 45 minutes there with
two thirds of a core, about 51 s per epoch of 5.3e12 flops on a whole core. A host 2.4x slower
per training step was 2.4x slower per epoch too (125 s on a whole core), so the hint scales with
the host's speed like the steps' estimates. Not a clean measurement: a hint."""
TYPICAL_EPOCHS = 60
"""Epochs a fit runs when only the patience stops it (a guess for the cost hint: MOPO's fit on
hopper-medium's 1M transitions ran past 35 epochs without stopping)."""


def fit_seconds(
    config: DynamicsConfig, obs_dim: int = 11, act_dim: int = 3, transitions: int = 1_000_000
) -> float:
    """A cost hint for sweeps: seconds :func:`fit` takes on ``transitions`` (hopper's shapes by
    default), ``max_epochs`` epochs or else :data:`TYPICAL_EPOCHS`, at :data:`FIT_FLOPS_PER_S`.
    Each epoch passes every member over the training split once, forward and backward
    (3 x 2 flops per weight and example)."""
    dims = (obs_dim + act_dim, *config.hidden_dims, 2 * (obs_dim + 1))
    weights = sum(a * b for a, b in zip(dims, dims[1:]))
    train = transitions - min(int(transitions * config.holdout_ratio), config.max_holdout)
    epochs = config.max_epochs or TYPICAL_EPOCHS
    return epochs * config.num_members * weights * train * 6 / FIT_FLOPS_PER_S


def select_members(mask: jax.Array, new: Params, old: Params) -> Params:
    """Members where ``mask`` is set from ``new``, the others from ``old`` (shared arrays: new)."""

    def pick(a, b):
        if a.ndim and a.shape[0] == mask.shape[0] and a.ndim > 1:
            return jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
        return a

    return {
        "net": jax.tree.map(pick, new["net"], old["net"]),
        **{name: new[name] for name in ("max_logvar", "min_logvar")},
    }


_select_members = jax.jit(select_members)


def disagreement(mean: jax.Array) -> jax.Array:
    """MOReL's disagreement: the largest distance between two members' predictions, ``[B]``
    (``mean: [K, B, d]``)."""
    diff = mean[:, None] - mean[None, :]
    return jnp.sqrt((diff**2).sum(-1)).max(axis=(0, 1))


def max_std_norm(logvar: jax.Array) -> jax.Array:
    """MOPO's penalty ``max_k |std_k(s, a)|_2`` (``penalty_learned_var``), ``[B]``."""
    return jnp.sqrt(jnp.exp(logvar).sum(-1)).max(axis=0)
