"""The shape of the code: no import circle in src/ or benchmarks/, no file in src/ too long to read
in one sitting.

An import circle (a module that, through others, imports itself) makes the order of imports
matter and hides which module a name belongs to; one closed by an import inside a function is a
circle all the same, so imports in function bodies count here too. The layers between packages
are import-linter's (tests/repository/test_layers.py); this checks every module against every other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[2]
MAX_LINES = 500
"""The longest a file in src/ may be."""


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph`` (module -> the modules it imports): each strongly connected
    component of more than one module, and each module that imports itself (Tarjan's algorithm,
    iterative so that a long chain does not reach Python's recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph.get(node, ()):
                    found.append(sorted(component))
    return found


def package_graph(name: str) -> dict[str, set[str]]:
    """``name``'s modules and what each imports of the package, at module level or in a
    function (grimp finds both)."""
    graph = grimp.build_graph(name)
    return {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}


def script_graph(folder: Path) -> dict[str, set[str]]:
    """The modules of a folder of scripts (each importable by its name, as the scripts put their
    folder on ``sys.path``) and what each imports of them, anywhere in its body."""
    modules = {}
    for path in sorted(folder.rglob("*.py")):
        parts = path.relative_to(folder).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = (path, parts[-1] == "__init__")
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from the package, up level - 1 packages
                    anchor = package.split(".") if package else []
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join([*anchor, *([base] if base else [])])
                targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
            for target in targets:
                while target and target not in modules:  # import a.b.c: the local a.b, or a
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def test_the_circle_finder_finds_circles():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []
    assert circles({"a": {"a"}}) == [["a"]]


def test_the_script_scan_sees_imports_in_functions(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "main.py").write_text("import pkg\n")
    (tmp_path / "pkg" / "__init__.py").write_text("from pkg.part import x\n")
    (tmp_path / "pkg" / "part.py").write_text("def f():\n    from main import y\n")
    graph = script_graph(tmp_path)
    assert graph == {"main": {"pkg"}, "pkg": {"pkg.part"}, "pkg.part": {"main"}}
    assert circles(graph) == [["main", "pkg", "pkg.part"]]


def test_no_import_circle_in_the_package():
    assert circles(package_graph("eabc")) == []


def test_no_import_circle_in_the_benchmarks():
    assert circles(script_graph(ROOT / "benchmarks")) == []


def test_no_file_in_src_is_longer_than_one_sitting():
    long = {
        str(path.relative_to(ROOT)): lines
        for path in sorted((ROOT / "src").rglob("*.py"))
        if (lines := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert long == {}, f"over {MAX_LINES} lines: split these by what they do"


OPTIONAL_EXTRAS = frozenset({"minari", "ray", "onnx", "d3rlpy"})
"""Packages of pyproject's extras: a module imports them where it needs them, so that the rest
works without them."""


def deferred_imports(source: str) -> list[tuple[int, str, str]]:
    """``(line, module, text)`` of every import inside a function or class body of ``source``
    (module-level ``try``/``if`` blocks count as the top)."""
    tree = ast.parse(source)
    lines = source.splitlines()
    found = []
    for scope in ast.walk(tree):
        if not isinstance(scope, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        for node in ast.walk(scope):
            if isinstance(node, ast.Import):
                module = node.names[0].name
            elif isinstance(node, ast.ImportFrom):
                module = "." * node.level + (node.module or "")
            else:
                continue
            found.append((node.lineno, module, lines[node.lineno - 1]))
    return sorted(set(found))


def unexplained(path: Path, source: str) -> list[str]:
    """Imports inside functions that are neither of an optional extra, nor in a command of the
    CLI (whose command modules import each command's rooms when the command runs, so that a
    parser is built without them), nor say on their line why they wait: ``# noqa: PLC0415
    (why)``."""
    command = path.parent.name == "cli"
    bad = []
    for line, module, text in deferred_imports(source):
        root = module.lstrip(".").split(".")[0]
        comment = text.partition("#")[2]
        if root in OPTIONAL_EXTRAS or command or "(" in comment:
            continue
        bad.append(
            f"{path.relative_to(ROOT) if path.is_absolute() else path}:{line}: {text.strip()}"
        )
    return bad


def test_the_import_scan_tells_a_reason_from_none():
    source = (
        "import os\n"
        "try:\n    import fcntl\nexcept ImportError:\n    fcntl = None\n"
        "def f():\n    import minari\n    import json\n"
        "    import jax  # noqa: PLC0415 (data workers stay free of JAX)\n"
        "class C:\n    def g(self):\n        from eabc import zoo  # noqa: PLC0415\n"
    )
    assert [m for _, m, _ in deferred_imports(source)] == ["minari", "json", "jax", "eabc"]
    assert [b.split(": ", 1)[1] for b in unexplained(Path("x.py"), source)] == [
        "import json",
        "from eabc import zoo  # noqa: PLC0415",
    ]
    assert unexplained(Path("cli/x.py"), source) == []


def test_imports_wait_inside_functions_only_for_a_stated_reason():
    """At the top of the module, unless an optional extra needs it, the CLI defers a command's
    rooms, or the line says why (the JAX-free data makers, a platform's fallback, an order that
    matters)."""
    bad = [
        problem
        for path in sorted((ROOT / "src" / "eabc").rglob("*.py"))
        for problem in unexplained(path, path.read_text())
    ]
    assert bad == [], "move these to the top, or say on the line why they wait:\n" + "\n".join(bad)
