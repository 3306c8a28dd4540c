"""Every ``eabc`` command README.md and docs/ tell a user to type parses and passes the checks the
command makes before it works (``eabc train`` through its ``--dry-run`` plan: dataset name,
algorithm settings, schedule), README's first command runs for real on a tiny budget, every
``python benchmarks/...`` command parses with its script's own parser, and every Python block runs."""

from __future__ import annotations

import json
import re
import shlex
import sys
from pathlib import Path

import pytest

from eabc import cli
from eabc.cli.experiments import sweep_spec
from eabc.cli.train import Train, train_plan
from eabc.data import generate
from eabc.experiments.spec import expand
from eabc.training.config import resolve_agent_config

ROOT = Path(__file__).resolve().parents[2]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
SHELL_FENCES = ("```bash", "```sh", "```shell", "```console")


def shell_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` of what a reader types: fenced shell blocks and indented code
    blocks (inline code names commands in the text; it is not typed); continuation lines
    joined."""
    lines, fence, pending, start = [], None, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            fence = None if fence else line.strip()
            continue
        if fence is None:
            if line.startswith("    ") and line.strip().startswith("eabc "):
                lines.append((number, line.strip()))
            continue
        if fence not in SHELL_FENCES:
            continue
        start = start or number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        lines.append((start, pending + line))
        pending, start = "", 0
    return lines


def eabc_commands(text: str) -> list[tuple[int, list[str]]]:
    """Each ``eabc ...`` command in ``text`` (after ``&&`` too) as its argument list."""
    commands = []
    for number, line in shell_lines(text):
        words, command = shlex.split(line, comments=True) + ["&&"], []
        for word in words:
            if word in ("&&", "||", ";", "|"):
                if command[:1] == ["eabc"]:
                    commands.append((number, command[1:]))
                command = []
            else:
                command.append(word)
    return commands


CASES = [
    pytest.param(argv, id=f"{doc.relative_to(ROOT)}:{number}")
    for doc in DOCUMENTS
    for number, argv in eabc_commands(doc.read_text())
]


def test_the_documents_have_commands():
    readme = [case for case in CASES if case.id.startswith("README.md:")]
    assert len(readme) >= 20 and readme[0].values[0][0] == "train"


@pytest.mark.parametrize("argv", CASES)
def test_a_documented_command_passes_its_checks(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # relative run directories land here, and none exists yet
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path / "cache"))  # no dataset made yet
    if "--help" in argv or "-h" in argv:
        with pytest.raises(SystemExit) as exit_:
            cli.parse(argv)
        assert exit_.value.code == 0
        return
    try:
        cmd = cli.parse(argv)
    except SystemExit as exit_:  # argparse's error: the line it printed says why
        pytest.fail(f"eabc {shlex.join(argv)}: {capsys.readouterr().err.strip().splitlines()[-1:]}")
        raise AssertionError from exit_
    if isinstance(cmd, Train) and not cmd.resume:
        config = cmd.config
        if config.dataset in generate.builtin_names():
            train_plan(cmd)  # the --dry-run's checks: settings resolved for the dataset
        else:  # the reader's own file or Minari id: the settings resolve for its name
            overrides = {k: v for k, v in vars(cmd.agent).items() if v is not None}
            resolve_agent_config(
                config.algo, Path(config.dataset).name, overrides | cli.parse_settings(cmd.set)
            )
    elif isinstance(cmd, cli.Sweep) and (cmd.spec is None or Path(cmd.spec).exists()):
        spec = sweep_spec(cmd)
        assert expand(spec), f"eabc {shlex.join(argv)} expands to no run"


def test_the_check_fails_on_a_broken_command():
    """The README's first command as it once was: an evaluation interval that is not a multiple
    of the log interval. Its check must fail, as the command did."""
    old = "pip install -e . && eabc train --dataset hopper-medium --algo eabc-ln --steps 10000 --eval-interval 2500"
    [(_, argv)] = eabc_commands(f"```bash\n{old}\n```\n")
    with pytest.raises(ValueError, match="--eval-interval must be a multiple of --log-interval"):
        cli.parse(argv)


def test_readme_first_command_runs(tmp_path, monkeypatch):
    """README's first command, for real, on a small dataset of the same name and a tiny budget
    (its length and intervals replaced)."""
    [(_, argv)] = eabc_commands((ROOT / "README.md").read_text())[:1]
    assert argv[0] == "train"
    monkeypatch.chdir(tmp_path)
    cache = tmp_path / "cache"
    monkeypatch.setenv("EABC_CACHE_DIR", str(cache))
    dataset = argv[argv.index("--dataset") + 1]
    generate.make(dataset, generate.dataset_path(dataset, cache), size=2_000)
    budget = {"--steps": "20", "--log-interval": "10", "--eval-interval": "20",
              "--checkpoint-interval": "20", "--eval-episodes": "1"}  # fmt: skip
    for flag, value in budget.items():  # a flag is given once: the README's value replaced
        if flag in argv:
            argv[argv.index(flag) + 1] = value
        else:
            argv += [flag, value]
    cli.main([*argv, "--no-progress"])
    [run_dir] = (tmp_path / "runs").iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["steps"] == 20 and summary["final_score"] == summary["final_score"]  # not NaN


def benchmark_commands(text: str) -> list[list[str]]:
    """Each ``python benchmarks/NAME.py ...`` a reader types (fenced shell blocks and indented
    code blocks), as its argument list from the script on."""
    lines = [line for _, line in shell_lines(text)]
    lines += [
        line for line in text.splitlines() if line.startswith("    ") and "benchmarks/" in line
    ]
    commands = []
    for line in lines:
        words = shlex.split(line, comments=True) + ["&&"]
        for i, word in enumerate(words[:-1]):
            if word == "python" and words[i + 1].startswith("benchmarks/"):
                end = next(j for j in range(i + 1, len(words)) if words[j] in ("&&", "|", ";"))
                commands.append(words[i + 1 : end])
    return commands


class _Parsed(Exception):
    """Raised once a script's command line parsed: the script stops before its work."""


def test_every_documented_benchmark_command_parses(monkeypatch):
    """``python benchmarks/...`` in README and docs/: the script exists and its own argument
    parser takes the arguments shown (a renamed or dropped flag fails here, not for a reader)."""
    import argparse  # noqa: PLC0415
    import runpy  # noqa: PLC0415

    commands = [argv for doc in DOCUMENTS for argv in benchmark_commands(doc.read_text())]
    assert len(commands) >= 5 and ["benchmarks/probe.py"] in commands
    real = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        real(self, args, namespace)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # the scripts import each other
    for argv in commands:
        monkeypatch.setattr(sys, "argv", argv)
        with pytest.raises(_Parsed):
            runpy.run_path(str(ROOT / argv[0]), run_name="__main__")


def python_blocks(text: str) -> list[str]:
    """The fenced ``python`` blocks of a Markdown text (at a line's start: not a fragment set
    inside a list, as docs/extending.md shows one)."""
    return re.findall(r"(?ms)^```python\n(.*?)^```", text)


README_BUDGET = "steps=50_000"
"""What README's Python block trains for, replaced here by a tiny budget."""


def test_the_python_blocks_run_as_a_reader_would_run_them(tmp_path, monkeypatch):
    """README's Python block (train, load the policy, act), then README's ONNX export and
    docs/deploy.md's block on the file it wrote, in one directory as a reader would, on a tiny
    dataset of the same name. Every Python block of README and docs/ is run: docs/datasets.md's
    (d3rlpy) by tests/data/test_d3rlpy.py, in d3rlpy's own environment."""
    blocks = {doc.relative_to(ROOT).as_posix(): python_blocks(doc.read_text()) for doc in DOCUMENTS}
    assert {doc for doc, found in blocks.items() if found} == {
        "README.md", "docs/deploy.md", "docs/datasets.md"
    }  # fmt: skip
    monkeypatch.chdir(tmp_path)
    cache = tmp_path / "cache"
    monkeypatch.setenv("EABC_CACHE_DIR", str(cache))
    generate.make("hopper-random", generate.dataset_path("hopper-random", cache), size=2_000)
    [readme] = blocks["README.md"]
    assert README_BUDGET in readme
    tiny = "steps=20, log_interval=10, eval_interval=20, checkpoint_interval=20, eval_episodes=1"
    namespace: dict = {}
    exec(readme.replace(README_BUDGET, tiny), namespace)  # noqa: S102
    assert namespace["summary"]["steps"] == 20
    assert namespace["action"].shape == namespace["env"].action_space.shape
    pytest.importorskip("onnxruntime")
    [export] = [argv for _, argv in eabc_commands((ROOT / "README.md").read_text())
                if argv[0] == "export-policy"]  # fmt: skip
    cli.main(export)
    [deploy] = blocks["docs/deploy.md"]
    exec(deploy, {})  # noqa: S102


def test_ci_runs_the_readme_test_command():
    """README's second command (install the test tools, run the suite) is what .ci/run runs, in
    a virtual environment .ci/run makes first, so the suite cannot see packages that the
    project's extras do not install; warnings are not hidden wholesale."""
    first_block = (ROOT / "README.md").read_text().split("```bash\n", 1)[1].split("```", 1)[0]
    install_and_test = first_block.splitlines()[1].split("#", 1)[0].strip()
    assert install_and_test == 'pip install -e ".[dev]" && python -m pytest'
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert install_and_test in ci
    before = ci[: ci.index(install_and_test)]
    assert "fresh_venv .ci/venv" in before and "pip install -q -e ." in before


def test_every_module_the_suite_imports_comes_from_an_extra():
    """The test tools are declared in the ``test`` extra and ``dev`` includes it: a test module
    importing a package that no extra installs fails in .ci/run's fresh environment, and this
    names it first."""
    import tomllib  # noqa: PLC0415 (Python 3.11+; the suite's own interpreter)

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    assert any(name.startswith("eabc[") and "test" in name for name in extras["dev"])
    declared = {
        req.split(">")[0].split("=")[0].split("[")[0].strip().lower().replace("-", "_")
        for group in (project["dependencies"], *extras.values())
        for req in group
    }
    imported = set()
    for path in (ROOT / "tests").rglob("*.py"):
        for line in path.read_text().splitlines():
            words = line.split()
            if len(words) >= 2 and words[0] in ("import", "from") and not line.startswith(" "):
                imported.add(words[1].split(".")[0].rstrip(","))
    local = {p.stem for folder in ("tests", "benchmarks") for p in (ROOT / folder).rglob("*.py")}
    local |= {"eabc", "probe_cases"}
    distributions = {"yaml": "pyyaml"}  # import names that differ from their distribution's
    missing = sorted(
        name
        for name in imported - local - set(sys.stdlib_module_names)
        if distributions.get(name, name).lower() not in declared
    )
    assert not missing, f"test modules import {missing}, which no extra of pyproject.toml installs"
