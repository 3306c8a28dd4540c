"""The cases of benchmarks/probe.py, one module per class or two, and the tiny runs and datasets
they copy (:mod:`probe_cases.common`)."""

from __future__ import annotations

from pathlib import Path

from probe_cases.bounds import interrupted, numbers_and_flags, output_paths
from probe_cases.case import Case
from probe_cases.common import make_base
from probe_cases.late import too_late
from probe_cases.malformed import malformed
from probe_cases.reports import no_reference_scores
from probe_cases.run_files import deleted_or_edited, foreign_files
from probe_cases.shapes import wrong_shapes
from probe_cases.tampered import tampered

__all__ = ["all_cases", "make_base"]


def all_cases(base: Path) -> list[Case]:
    """Every case of the probe, class by class."""
    return [*foreign_files(base), *deleted_or_edited(base), *malformed(base), *too_late(base),
            *wrong_shapes(base), *no_reference_scores(base), *tampered(base),
            *numbers_and_flags(base), *output_paths(base), *interrupted(base)]  # fmt: skip
