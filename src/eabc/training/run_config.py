"""A training run's ``config.json``, checked by one model wherever it is read.

Resume, evaluate, ``load_policy``, the ONNX export and ``eabc results`` read a run's config.json
through :func:`read`, which checks it against :class:`RunConfigFile` before anything uses it: no
key this package never writes, each train setting of the type and range
:class:`~eabc.training.config.TrainConfig` declares for it (and the settings together, as
TrainConfig checks them), and the agent settings as the algorithm's config declares them
(:func:`eabc.ranges.validated`), in the words the command line and a sweep spec use. A
hand-edited file (``{}``, a key missing or added, a string where a number belongs, a list where a
mapping belongs) is refused in one line that names the file, the key and what to do
(:class:`ConfigError`), rather than raising ``KeyError`` deep in a reader.

Files of earlier versions keep loading: every version wrote ``train`` with all of TrainConfig's
fields, ``agent``, ``dataset`` and ``max_action`` (the first three are required: without them the
file does not say how the run was made); ``run_id`` (runs from before run ids) and
``dataset.fingerprint`` (runs from before the data check) may be absent, and agent settings a later
version added take the preset's value (those it removed are ignored), as resume always did. Of the
train settings only what identifies a run (``dataset``, ``algo``, ``seed``) and its length
(``steps``) are required; another that is absent reads as TrainConfig's default. A run whose
checkpoint records its identity is still refused then when the settings hash differs
(:mod:`eabc.training.identity` names the absent keys).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path
from typing import Annotated, Any

import pydantic

from eabc import ranges
from eabc.agents import ALGORITHMS
from eabc.data.dataset import reference_scores_problem
from eabc.training.checkpoint import CONFIG, read_config
from eabc.training.config import TrainConfig

REQUIRED = ("dataset", "algo", "seed", "steps")
"""Train settings without which a config.json does not say which run it is or how long it is."""
_REDO = "or restore config.json from a copy"


class ConfigError(ValueError):
    """A config.json this package cannot use; the message names the file, the key and what to do."""


FiniteNumber = Annotated[float, pydantic.Field(allow_inf_nan=False)]
"""A finite number (JSON lets NaN and Infinity through as numbers)."""


class _Strict(pydantic.BaseModel):
    """No conversion (``"200"`` is not 200, ``true`` is not 1), no key the package never wrote."""

    model_config = pydantic.ConfigDict(extra="forbid", strict=True, frozen=True)


class DatasetSection(_Strict):
    """What the run was trained on, recorded when it started."""

    name: str | None = None
    """The dataset's name (hopper-medium, or a file's stem)."""
    size: ranges.NonNegative | None = None
    """Its number of transitions: resume refuses data of another size."""
    fingerprint: str | None = None
    """Its content's SHA-256 (absent in runs from before the check)."""
    env_id: str | None = None
    """The Gymnasium id the run evaluates in."""
    ref_min_score: FiniteNumber | None = None
    """The return that scores 0 (None: the data has no reference scores)."""
    ref_max_score: FiniteNumber | None = None
    """The return that scores 100: above ref_min_score, as the data's own are."""

    @pydantic.model_validator(mode="after")
    def _ordered(self) -> DatasetSection:
        problem = reference_scores_problem(self.ref_min_score, self.ref_max_score)
        if problem:
            raise ValueError(problem)
        return self


class RunConfigFile(_Strict):
    """The whole of a training run's config.json."""

    run_id: str | None = None
    """The run's random id (:mod:`eabc.training.identity`; absent in runs from before ids)."""
    train: dict[str, Any]
    """TrainConfig's fields (:func:`train_model` checks them)."""
    agent: dict[str, Any]
    """The algorithm's resolved settings (checked by its config's declaration)."""
    dataset: DatasetSection
    """What the run was trained on."""
    max_action: Annotated[float, pydantic.Field(gt=0, allow_inf_nan=False)] | None = None
    """The environment's action bound (the policy's output scale): a finite number > 0, the
    evaluation environment's own (:func:`check_max_action`)."""


def check_max_action(config: dict, path: Path, env) -> None:
    """Refuse a recorded ``max_action`` that is not ``env``'s action bound (what eabc wrote):
    the policy's actions are ``max_action * tanh(...)``, so another value would act outside
    the environment's bounds, or within a part of them only."""
    recorded = config.get("max_action")
    bound = float(env.action_space.high[0])
    if recorded is not None and not math.isclose(recorded, bound, rel_tol=1e-6):
        raise ConfigError(
            f"{path}: max_action is {recorded}, but {env.spec.id}'s actions are bounded by "
            f"{bound} (its action_space.high); put back {bound} {_REDO}"
        )


@functools.cache
def train_model() -> type[pydantic.BaseModel]:
    """TrainConfig's keys as a strict model: :data:`REQUIRED` required, no other key; the values
    are TrainConfig's to check (:func:`check`), by the types it declares."""
    fields: dict[str, Any] = {
        field.name: (Any, ... if field.name in REQUIRED else field.default)
        for field in dataclasses.fields(TrainConfig)
    }
    return pydantic.create_model("TrainSection", __base__=_Strict, **fields)


def check(config: dict, path: Path) -> dict:
    """``config`` (the JSON object read from ``path``) if it is a run's config.json, else
    :class:`ConfigError` in one line naming ``path``, the first bad key and what to do."""
    try:
        RunConfigFile.model_validate(config)
    except pydantic.ValidationError as error:
        raise ConfigError(_message(error.errors()[0], path)) from None
    try:
        train_model().model_validate(config["train"])
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        raise ConfigError(_message({**first, "loc": ("train", *first["loc"])}, path)) from None
    train = config["train"]
    try:  # each of its declared type and range (no conversion), and together, as TrainConfig's
        TrainConfig(**{**train, "cache_dir": None})
    except ValueError as error:
        raise ConfigError(
            f"{path}: train.{error}; put back the value the run was started with {_REDO}"
        ) from None
    algorithm = ALGORITHMS[train["algo"]]
    preset = algorithm.preset
    known = algorithm.settings() | set(ranges.groups(type(preset)))
    settings = {k: v for k, v in config.get("agent", {}).items() if k in known}
    try:  # settings of older versions that this one dropped are ignored, as resume does
        ranges.validated(preset, settings, f"{algorithm.name} setting ")
    except ranges.SettingError as error:
        raise ConfigError(
            f"{path}: agent: {error}; put back the value the run was started with {_REDO}"
        ) from None
    return config


def _message(error: dict, path: Path) -> str:
    where = ".".join(str(part) for part in error["loc"])
    kind, text = error["type"], error["msg"].removeprefix("Value error, ")
    text = text.replace(" or instance of DatasetSection", "")
    if kind == "missing":
        return (
            f"{path}: {where} is missing; put it back as the run was started (every eabc "
            f"writes it) {_REDO}"
        )
    if kind == "extra_forbidden":
        return f"{path}: {where} is not a key of a run's config.json; remove it"
    got = "" if kind == "value_error" else f", got {error.get('input')!r}"
    return (
        f"{path}: {where}: {text[0].lower()}{text[1:]}{got}; put back the value the run was "
        f"started with {_REDO}"
    )


def read(run_dir: str | Path) -> dict:
    """A training run's config.json, checked (:func:`check`); the object as the file holds it."""
    return check(read_config(run_dir), Path(run_dir) / CONFIG)
