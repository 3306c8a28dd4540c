"""What the commands share: parsing a checked config's flags, the algorithm flags made from the
contracts, and ``KEY=VALUE`` settings."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import operator
import re
import types
import typing
from typing import Annotated

import tyro

from eabc import ranges
from eabc.training.config import TrainConfig
from eabc.training.online import SACTrainConfig


def _parsed_unchecked(config_class: type) -> type:
    """``config_class`` without its ``__post_init__`` checks, for parsing only.

    tyro reports an error raised while it builds a nested dataclass under the dataclass's internal
    name (``__tyro-dummy-inner__.config``); checked in :func:`_checked` instead, the message can
    name the user's flags (``--eval-interval must be a multiple of --log-interval=300``).
    """
    namespace = {"__post_init__": lambda self: None, "__doc__": config_class.__doc__}
    return dataclasses.dataclass(frozen=True)(
        type(config_class.__name__, (config_class,), namespace)
    )


def _checked(options, config_class: type):
    """The parsed ``options`` as a checked ``config_class``; field names in errors as flags."""
    values = {f.name: getattr(options, f.name) for f in dataclasses.fields(config_class)}
    try:
        return config_class(**values)
    except ValueError as error:
        message = str(error)
        for name in values:
            message = re.sub(rf"\b{name}\b", "--" + name.replace("_", "-"), message)
        raise ValueError(message) from None


def quiet_unset_defaults(cls: type) -> type:
    """``cls`` (a command's dataclass, and the dataclasses in its fields) without tyro's
    ``(default: None)`` after an option whose default is None (its help says what unset means:
    ``default runs/DATASET_ALGO_seedS``, ``Unset: the preset's``; None cannot be typed) or
    ``(default: )`` after an empty list, and its docstrings' paragraphs each on one line (tyro
    1.0 keeps the line break before every indented docstring line: help cut mid-sentence)."""
    from eabc.agents.contract import field_docs  # noqa: PLC0415

    if cls.__doc__:
        paragraphs = re.split(r"\n\s*\n", cls.__doc__.strip())
        cls.__doc__ = "\n\n".join(" ".join(paragraph.split()) for paragraph in paragraphs)
    hints = typing.get_type_hints(cls, include_extras=True)
    own = dict(cls.__dict__.get("__annotations__", {}))
    docs = field_docs(cls)
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        inner = typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint
        if dataclasses.is_dataclass(inner):
            quiet_unset_defaults(inner)
            continue
        default = field.default
        if field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        empty = default is None or (isinstance(default, list | tuple) and not default)
        extras = typing.get_args(hint)[1:] if typing.get_origin(hint) is Annotated else ()
        given = any(getattr(extra, "help", None) for extra in extras)  # a help made in code wins
        help_text = None if given else docs.get(field.name)
        marks = {"help": help_text, "help_behavior_hint": "" if empty else None}
        if any(value is not None for value in marks.values()):
            own[field.name] = Annotated[hint, tyro.conf.arg(**marks)]
    cls.__annotations__ = own
    return cls


def check_flags(cmd) -> None:
    """Every flag of ``cmd`` whose type carries a range (:mod:`eabc.ranges`: ``Positive``,
    ``Seed``, ...) within it; ``ValueError`` naming the flag (``--episodes must be an integer >= 1,
    got 0``). The train options are the config's own checks (:func:`_checked`)."""
    hints = typing.get_type_hints(type(cmd), include_extras=True)
    for field in dataclasses.fields(cmd):
        if ranges.constrained(hints[field.name]):
            flag = "--" + field.name.replace("_", "-")
            ranges.check(getattr(cmd, field.name), hints[field.name], flag)


_KINDS = {"INT": "an integer", "FLOAT": "a number", "[INT [INT ...]]": "whole numbers",
          "[FLOAT [FLOAT ...]]": "numbers"}  # fmt: skip
"""What tyro's metavars mean, in words."""


class FlagError(ValueError):
    """A flag tyro could not parse, said in one line (its value, and what it takes)."""


@contextlib.contextmanager
def one_line_errors(argv: list[str], prog: str):
    """tyro's parse errors as one :class:`FlagError` line naming the flag, the bad value and what
    the flag takes (its choices, or the kind of number), where tyro would draw a box of many
    lines. tyro's hook for this is private (``tyro._errors``, tyro >= 1.0); without it tyro's own
    box is printed, as before."""
    errors = getattr(tyro, "_errors", None)
    if errors is None or not hasattr(errors, "on_parse_error"):
        yield
        return

    def flag_of(argument) -> str:
        if argument.is_positional() or not argument.lowered.name_or_flags:
            return str(argument.lowered.metavar)
        return "/".join(argument.lowered.name_or_flags)

    def hook(event) -> None:
        argument = getattr(event, "argument", None)
        if isinstance(event, errors.InvalidChoice):
            choices = sorted(c for c in event.choices if c != "None")
            raise FlagError(
                f"{flag_of(argument)} {event.value!r} is not one of its choices: "
                f"{', '.join(choices)}"
            )
        if isinstance(event, errors.InstantiationFailure) and argument is not None:
            flag = flag_of(argument)
            metavar = str(argument.lowered.metavar)
            kind = _KINDS.get(metavar, f"a value of the form {metavar}")
            value = _given(argv, argument.lowered.name_or_flags)
            got = f", got {value!r}" if value is not None else f" ({event.message.splitlines()[0]})"
            raise FlagError(f"{flag} must be {kind}{got}")
        if isinstance(event, errors.BadValue) and event.reason == "too_few_values":
            raise FlagError(f"{flag_of(argument)} needs a value; see `{prog} --help`")
        if isinstance(event, errors.UnrecognizedArgs):
            raise FlagError(
                f"unrecognized argument(s) {' '.join(event.tokens)}; see `{prog} --help` for "
                "the flags and their values"
            )
        if isinstance(event, errors.MissingArgs):
            missing = [flag_of(context.arg) for context in event.missing_arguments]
            raise FlagError(f"{prog} needs {', '.join(missing)}; see `{prog} --help`")

    with errors.on_parse_error(hook):
        yield


def _given(argv: list[str], names: tuple[str, ...]) -> str | None:
    """The value ``argv`` gives the flag ``names`` (``--flag VALUE...`` or ``--flag=VALUE``)."""
    for i, token in enumerate(argv):
        for name in names:
            if token.startswith(name + "="):
                return token.split("=", 1)[1]
            if token == name:
                values = []
                for value in argv[i + 1 :]:
                    if value.startswith("--"):
                        break
                    values.append(value)
                return " ".join(values)
    return None


def check_agent(config, agent, items: tuple[str, ...]) -> None:
    """`eabc train`'s algorithm settings (its typed flags ``agent`` and ``--set`` ``items``)
    checked against ``config.algo``'s own, before any work; ``ValueError`` naming the flag
    (``--num-critics``) or ``--set``."""
    from eabc.agents import get_algorithm  # noqa: PLC0415

    algorithm = get_algorithm(config.algo)
    flags = {k: v for k, v in dataclasses.asdict(agent).items() if v is not None}
    settings = parse_settings(items)
    both = sorted(set(flags) & set(settings))
    if both:  # which one wins would be a silent choice
        flag = "--" + both[0].replace("_", "-")
        raise ValueError(
            f"{flag} {flags[both[0]]} and --set {both[0]}=... both set {both[0]}; give it once"
        )
    for source, names in (("--set: ", settings), ("", flags)):
        unknown = sorted(set(names) - algorithm.settings())
        if unknown:
            named = source or " ".join("--" + name.replace("_", "-") for name in unknown) + ": "
            raise ValueError(
                f"{named}{algorithm.name} has no setting(s) {unknown}; it has "
                f"{sorted(algorithm.settings())}"
            )
    try:  # converted and checked by the config's own declaration, as a spec's are
        ranges.validated(algorithm.preset, flags | settings, f"{algorithm.name} setting ")
    except ValueError as error:
        message = str(error)
        for name in flags:
            message = re.sub(rf"\b{name}\b", "--" + name.replace("_", "-"), message)
        raise ValueError(message if message != str(error) else f"--set: {message}") from None


def _algorithm_names_in_help(cls: type) -> type:
    """``cls`` whose ``--algo`` help lists the registered algorithms, in the registry's order:
    the list follows the registry, so adding an algorithm adds it here."""
    from eabc.agents import ALGORITHMS  # noqa: PLC0415

    names = f"{', '.join(list(ALGORITHMS)[:-1])} or {list(ALGORITHMS)[-1]}"
    help_text = f"Algorithm: {names} (docs/algorithms.md describes each)."
    namespace = {
        "__annotations__": {"algo": Annotated[str, tyro.conf.arg(help=help_text)]},
        "algo": cls.algo,
        "__doc__": cls.__doc__,
    }
    return dataclasses.dataclass(frozen=True)(type(cls.__name__, (cls,), namespace))


TrainOptions = _algorithm_names_in_help(_parsed_unchecked(TrainConfig))
SACTrainOptions = _parsed_unchecked(SACTrainConfig)


def _agent_overrides() -> type:
    """The typed algorithm flags of ``eabc train``, made from the algorithm contracts: every
    setting some algorithm lists in ``cli_flags``, unset by default (the preset's value)."""
    from eabc.agents import ALGORITHMS  # noqa: PLC0415
    from eabc.agents.contract import field_docs  # noqa: PLC0415

    fields, users = {}, {}
    for algorithm in ALGORITHMS.values():
        hints = typing.get_type_hints(type(algorithm.preset))
        docs = field_docs(type(algorithm.preset))
        for name in algorithm.cli_flags:
            users.setdefault(name, []).append(
                f"{algorithm.name}: {getattr(algorithm.preset, name)}"
            )
            fields.setdefault(name, (hints[name], docs.get(name, "")))
    spec = []
    for name, (hint, doc) in fields.items():
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = typing.get_origin(hint) in (typing.Union, types.UnionType)
        inner = functools.reduce(operator.or_, args) if optional else hint  # noqa: E501
        where = "; ".join(users[name]).replace(": None", ": Table 3's")
        help_text = f"{doc} Unset: the preset's ({where})."
        spec.append((name, Annotated[inner | None, tyro.conf.arg(help=help_text)], None))
    return dataclasses.make_dataclass(
        "AgentOverrides",
        spec,
        frozen=True,
        namespace={"__doc__": "Algorithm settings to change from the preset --algo chose."},
    )


AgentOverrides = _agent_overrides()


def parse_settings(items: tuple[str, ...], flag: str = "--set") -> dict:
    """``KEY=VALUE`` strings as settings; a comma makes a tuple (``hidden_dims=512,512``). A key
    given twice is refused: which of its values was meant is not for the parser to guess."""
    settings, given = {}, {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"bad {flag} {item!r}; use KEY=VALUE")
        if key in given:
            raise ValueError(
                f"{flag} gives {key} twice ({given[key]} and {item}); give each setting once"
            )
        given[key] = item
        parts = [parse_value(v) for v in value.split(",")]
        settings[key] = tuple(parts) if "," in value else parts[0]
    return settings


def parse_value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


RESUME_OPTIONS = {"resume", "restart", "progress", "no-progress", "dry-run", "eval-workers"}
"""What ``--resume`` takes beside it: the run's own config.json says everything else."""


def refuse_ignored_with_resume(argv: list[str], allowed: set[str] = RESUME_OPTIONS) -> None:
    """``ValueError`` naming the flags of ``argv`` that ``--resume`` would ignore (``--seed``,
    ``--steps``, ``--set``, ...): a resumed run keeps the settings it was started with, so a flag
    that seems to change them is refused rather than dropped without a word."""
    given = []
    for token in argv:
        name = token[2:].split("=", 1)[0] if token.startswith("--") else None
        if name and name not in allowed and "--" + name not in given:
            given.append("--" + name)
    if given:
        raise ValueError(
            f"--resume continues a run with the settings in its config.json, so {', '.join(given)}"
            " would be ignored: leave them out, or start a new run (without --resume) in another"
            " --run-dir"
        )


def refuse_repeated_flags(argv: list[str]) -> None:
    """``ValueError`` naming a flag ``argv`` gives twice (``--seed 1 --seed 2``, ``--set a=1
    --set a=2``, ``--progress --no-progress``): the parser would keep the last without a word."""
    seen: dict[str, str] = {}
    for token in argv:
        if not token.startswith("--") or token == "--":
            continue
        flag = token.split("=", 1)[0]
        key = flag.removeprefix("--no-").removeprefix("--")
        if key in seen and seen[key] != flag:
            raise ValueError(f"{seen[key]} and {flag} are both given; give one of them")
        if key in seen:
            raise ValueError(
                f"{flag} is given twice; give each flag once (a flag of several values takes "
                "them all after it, e.g. --set a=1 b=2)"
            )
        seen[key] = flag


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, said in one line with what to do next (``eabc`` exits with 130, as a shell does
    for SIGINT): ``interrupted at step 3000; resume with: eabc train --resume runs/x``."""
