"""Algorithms know themselves: generic code (the training loop, experiments and reports,
evaluation) names no registered algorithm. What is particular to one (its label, reward
convention, paper defaults, comparison baseline, advice on a failed run) lives in its own file
behind :class:`eabc.agents.contract.Algorithm`, so adding an algorithm touches its file and one
registry line, and nothing here."""

from __future__ import annotations

import io
import re
import token
import tokenize
from pathlib import Path

from eabc.agents import ALGORITHMS, MODULES

ROOT = Path(__file__).resolve().parents[2]
GENERIC = ("src/eabc/training", "src/eabc/experiments", "src/eabc/evaluation.py")
"""What may ask an algorithm's description but never name one."""
PROGRAM_COMMANDS = (
    "train", "evaluate", "sac", "export-policy", "sweep", "results", "report", "study", "data",
    "zoo", "--help", "--version",
)  # fmt: skip
PROGRAM = re.compile(
    rf"\beabc(?= ({'|'.join(PROGRAM_COMMANDS)})\b)"  # the program: eabc sweep
    r"|\beabc(?=[/\[])|(?<=/)eabc\b"  # eabc/AntMaze-UMaze-v0, pip install 'eabc[ray]', ~/.cache/eabc
    r"|\bEABC_[A-Z_]+"  # its environment variables: $EABC_CACHE_DIR
    r"|\b(version of|algorithm of|older|every) eabc\b|\beabc (wrote|writes)\b"  # the program
)
"""Where the program's name, which is also its first algorithm's, names the program or package."""
CLONING_TERM = re.compile(
    r"BC\s+(term|fraction|weight|rule)s?\b|\bbc_(fraction|weight)|(?<=[a-z}])_bc\b"
)
"""The behaviour-cloning term that many algorithms share (its weight, the fraction of samples
with it on, a table's ``{side}_bc`` column) is vocabulary of the field, not the algorithm BC."""


def _words() -> list[str]:
    words = {w for a in ALGORITHMS.values() for w in (a.name, a.display_name)}
    return sorted(words, key=len, reverse=True)


def _word_pattern() -> re.Pattern:
    # A name stands alone: letters, digits, hyphens and "+" join it to a longer word (eabc-ln is
    # not eabc, TD3+BC is neither TD3 nor BC, iql-scale is a reward convention); an underscore
    # does not (a run id, hopper-medium__eabc__K5__seed0), nor a dot before a letter (eabc.data).
    alternatives = "|".join(re.escape(w) for w in _words())
    return re.compile(rf"(?<![A-Za-z0-9+-])({alternatives})(?![A-Za-z0-9+-]|\.[A-Za-z])")


def _names_in_text(text: str, pattern: re.Pattern) -> list[str]:
    text = PROGRAM.sub(" ", CLONING_TERM.sub(" ", text))
    return [match.group() for match in pattern.finditer(text)]


def _names_in_identifier(name: str, previous: str, following: str) -> list[str]:
    if name == "eabc" and previous != "." and (previous in ("import", "from") or following == "."):
        return []  # the package (eabc.agents.eabc's last part is the algorithm's module)
    found = [a.name for a in ALGORITHMS.values() if name == a.name.replace("-", "_")]
    for algorithm in ALGORITHMS.values():  # a class named for one: EABCConfig, TD3BCConfig
        stem = re.sub(r"\W", "", algorithm.display_name)
        if re.fullmatch(rf"{re.escape(stem)}[A-Z][a-z]\w*", name):
            found.append(algorithm.display_name)
    return found


def algorithm_names(source: str) -> list[tuple[int, str]]:
    """``(line, name)`` for every registered algorithm's name or display label in ``source``: in
    a string, a comment or a docstring (standing alone as a word), or as an identifier."""
    pattern = _word_pattern()
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    found = []
    for i, tok in enumerate(tokens):
        if tok.type in (token.STRING, token.COMMENT) or tok.type == getattr(
            token, "FSTRING_MIDDLE", None
        ):
            if [t.string for t in tokens[max(i - 2, 0) : i]] in (["version", "("], ["files", "("]):
                continue  # the package: metadata.version("eabc"), resources.files("eabc")
            text = tok.string
            if tok.type == getattr(token, "FSTRING_MIDDLE", None) and tokens[i - 1].string == "}":
                text = "}" + text  # Python 3.12 splits f"{side}_bc" where 3.11 kept one string
            names = _names_in_text(text, pattern)
        elif tok.type == token.NAME:
            previous = tokens[i - 1].string if i else ""
            following = tokens[i + 1].string if i + 1 < len(tokens) else ""
            names = _names_in_identifier(tok.string, previous, following)
        else:
            continue
        found += [(tok.start[0], name) for name in names]
    return found


def _generic_files() -> list[Path]:
    files = []
    for part in GENERIC:
        path = ROOT / part
        files += sorted(path.rglob("*.py")) if path.is_dir() else [path]
    return files


def test_generic_code_names_no_algorithm():
    found = [
        f"{path.relative_to(ROOT)}:{line}: {name}"
        for path in _generic_files()
        for line, name in algorithm_names(path.read_text(encoding="utf-8"))
    ]
    assert not found, "generic code names an algorithm; ask its description instead:\n" + "\n".join(
        found
    )


def test_the_scan_finds_names_where_they_hide_and_not_the_package():
    source = '''"""Compare against TD3+BC (``eabc train --algo td3bc``)."""
import eabc.agents
from eabc import agents
from eabc.agents import iql

x = eabc.agents.ALGORITHMS  # EABC's own rule
DEFAULTS = {"eabc-ln": "raw"}
label = f"{x} over sac-n"
env = "eabc/AntMaze-UMaze-v0"
config: EABCConfig
share = "BC fraction"  # the BC term, bc_weight
run = "hopper-medium__eabc__K5"
from eabc.agents.eabc import RECOMMENDED
cache = os.environ.get("EABC_CACHE_DIR", "~/.cache/eabc")  # an older eabc wrote it
version = metadata.version("eabc")
side = f"{side}_bc"
'''
    names = [name for _, name in algorithm_names(source)]
    assert names == ["TD3+BC", "td3bc", "iql", "EABC", "eabc-ln", "sac-n", "EABC", "eabc", "eabc"]


def test_every_registered_algorithm_is_in_the_registry_and_labelled_once():
    """Adding an algorithm is its file and one entry of ``MODULES``: each module's descriptions
    are registered, and names and labels are unique (the scan and reports key on them)."""
    registered = [a.name for module in MODULES for a in module.ALGORITHMS]
    assert registered == list(ALGORITHMS)
    labels = [a.display_name for a in ALGORITHMS.values()]
    assert len(set(labels)) == len(labels)
