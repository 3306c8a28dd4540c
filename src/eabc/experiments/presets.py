"""The sweep presets (``eabc sweep --preset NAME``): the paper's grids and the study's, read from
``presets/sweeps.yaml``, shipped with the package.

A preset is a sweep specification (:mod:`eabc.experiments.spec`), data about an experiment: the
file names the algorithms it runs, as any spec file does, and this module names none. There
``datasets: mujoco`` and ``datasets: antmaze`` stand for the built-in datasets of the paper's
Table 1 and Table 5 (:func:`eabc.data.generate.mujoco_names`, :func:`~eabc.data.generate.antmaze_names`).
"""

from __future__ import annotations

import copy
from importlib import resources
from typing import Any

import yaml

from eabc.data import generate

SOURCE = resources.files("eabc") / "presets" / "sweeps.yaml"
"""The presets' file, in the installed package."""
DATASET_GROUPS = {"mujoco": generate.mujoco_names, "antmaze": generate.antmaze_names}
"""What ``datasets: NAME`` stands for in a preset."""


def load(text: str) -> dict[str, dict[str, Any]]:
    """The presets in ``text`` (the YAML of :data:`SOURCE`), by name, each its own copy."""
    presets = {}
    for name, spec in yaml.safe_load(text).items():
        spec = copy.deepcopy(spec)  # YAML aliases share one object; each preset owns its own
        if isinstance(spec.get("datasets"), str):
            spec["datasets"] = DATASET_GROUPS[spec["datasets"]]()
        presets[name] = spec
    return presets


PRESETS: dict[str, dict[str, Any]] = load(SOURCE.read_text(encoding="utf-8"))
"""Every preset by name, in the file's order."""
