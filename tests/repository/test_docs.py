"""The repository stands alone and its documentation stays true to it: nothing points outside the
repository, every relative link and anchor in the Markdown resolves, the file map names every
module, one committed format per result, and a README short enough to read."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCANNED = ("src", "tests", "benchmarks", "docs")
TEXT = {".py", ".md", ".sh", ".yaml", ".yml", ".toml", ".txt", ".json", ".cfg"}
OUTSIDE = re.compile(r"\.\./shared|SPEC\.md|\bSPEC\b")
"""A pointer to the spec that lived beside the repository (``../shared/SPEC.md``, "SPEC section
5"). The sweep's Python name ``SPEC`` (``sweep.json``) and the CLI's placeholder are not."""
PYTHON_NAME = re.compile(r"(\.|/ |\{|\"|eabc (sweep|study) )$")
"""What stands before ``SPEC`` where it is a Python name or a placeholder: ``sweep.SPEC``,
``run_dir / SPEC``, ``f"*/{SPEC}"``, ``metavar="SPEC"``, ``eabc sweep SPEC``."""


def _texts():
    paths = [ROOT / "README.md"]
    for folder in SCANNED:
        paths += [p for p in (ROOT / folder).rglob("*") if p.suffix in TEXT and p.is_file()]
    for path in paths:
        if ".egg-info" in str(path) or "__pycache__" in path.parts:
            continue
        if path.resolve() == Path(__file__).resolve():
            continue  # this file names what it looks for
        yield path, path.read_text(encoding="utf-8", errors="replace")


def _pointers_outside(text: str) -> list[str]:
    found = []
    for line in text.splitlines():
        for match in OUTSIDE.finditer(line):
            before, after = line[: match.start()], line[match.end() :]
            if match.group() == "SPEC" and (
                PYTHON_NAME.search(before) or re.match(r"\s*(=[^=]|[})\],\"])", after)
            ):
                continue
            found.append(line.strip())
    return found


def test_nothing_points_outside_the_repository():
    offenders = {
        str(path.relative_to(ROOT)): lines
        for path, text in _texts()
        if (lines := _pointers_outside(text))
    }
    assert not offenders, f"pointers to files outside the repository: {offenders}"


def test_the_outside_pointer_check_can_fail():
    assert _pointers_outside("see ../shared/SPEC.md section 1")
    assert _pointers_outside("``bc_weight`` (SPEC section 5)")
    assert _pointers_outside("as SPEC pins it")
    assert not _pointers_outside('SPEC = "sweep.json"')
    assert not _pointers_outside("(run_dir / sweep.SPEC).write_text(...)")
    assert not _pointers_outside("eabc sweep SPEC --root ROOT")
    assert not _pointers_outside('for spec_file in sorted((root / RUNS).glob(f"*/{SPEC}")):')


def _slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"(?ms)^```.*?^```", "", path.read_text(encoding="utf-8"))
    return {_slug(m) for m in re.findall(r"(?m)^#+\s+(.*)$", text)}


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_every_relative_link_in_the_markdown_resolves():
    broken = []
    for page in _markdown_files():
        text = re.sub(r"(?ms)^```.*?^```", "", page.read_text(encoding="utf-8"))
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue  # http:, https:, mailto:
            file, _, anchor = target.partition("#")
            resolved = (page.parent / file).resolve() if file else page
            if not resolved.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, broken


def test_code_points_into_the_algorithm_page_at_headings_that_exist():
    """``docs/algorithm.md#section`` in code and tests names a heading of that page."""
    anchors = _anchors(ROOT / "docs" / "algorithm.md")
    for path, text in _texts():
        for anchor in re.findall(r"docs/algorithm\.md#([\w-]+)", text):
            assert anchor in anchors, f"{path.relative_to(ROOT)}: algorithm.md#{anchor}"


DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
"""A calendar date. The docs read without them; the hardware a figure ran on stays, and the
provenance data under docs/results (JSON, CSV) keeps its dates."""


def test_the_markdown_names_no_calendar_dates():
    dated = [
        f"{page.relative_to(ROOT)}:{number}: {line.strip()}"
        for page in _markdown_files()
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if DATE.search(line)
    ]
    assert not dated, dated


def test_the_date_check_can_fail():
    assert DATE.search("measured on the Zen 5 host, 2026-12-02 07:26 UTC")
    assert not DATE.search("EABC's / 1.24 (1.13-1.24), K = 10, 2-4x slower")


def _file_map() -> str:
    text = (ROOT / "docs" / "extending.md").read_text(encoding="utf-8")
    section = text[text.index("## Where things are") :]
    return section.split("```")[1].split("\nbenchmarks/")[0]  # the package's part


def _mapped_modules(block: str) -> set[str]:
    """``agents/bc.py, wpc.py   baselines`` names agents/bc.py and agents/wpc.py."""
    named = set()
    for line in block.splitlines():
        entries = re.match(r"[\w/.]+(?:, [\w/.]+)*", line.strip())
        folder = ""
        for entry in entries.group().split(", ") if entries else ():
            if "/" in entry:
                folder = entry.rpartition("/")[0] + "/"
                named.add(entry)
            else:
                named.add(folder + entry)
    return named


def _holds_code(path: Path) -> bool:
    """Whether a module holds more than a docstring (an empty package's ``__init__.py`` does not
    need a line of its own in the map)."""
    body = ast.parse(path.read_text(encoding="utf-8")).body
    return any(not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)) for n in body)


def test_the_file_map_names_every_module():
    modules = {
        str(p.relative_to(ROOT / "src" / "eabc"))
        for p in (ROOT / "src" / "eabc").rglob("*.py")
        if "__pycache__" not in p.parts and _holds_code(p)
    }
    named = _mapped_modules(_file_map())
    assert modules - named == set(), "docs/extending.md's file map misses these modules"
    assert {m for m in named if m.endswith(".py")} - modules == set(), "the map names gone files"


def test_results_keep_one_format_per_figure_and_table():
    """PNG figures and Markdown tables; PDF, SVG, HTML and LaTeX come from eabc report
    --formats on demand."""
    duplicates = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "docs").rglob("*")
        if p.suffix in {".pdf", ".svg", ".html", ".tex"}
    ]
    assert not duplicates


def test_the_readme_stays_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines < 300, f"README.md has {lines} lines: move detail into docs/"
