"""The layout by role stays as docs/architecture.md draws it: ``resireg_train``'s top level holds
packages only, every package's docstring says what may import it, the architecture page stays
short and names every package, every package of ``resireg_train`` has its floor in the import
contract, and no module imports itself back through others (imports inside functions
counted)."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pytest's own dependency before Python 3.11
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"


def _packages() -> list[str]:
    """Every package of the checkout, dotted (``resireg.models.vlm``)."""
    found = []
    for init in sorted(SRC.rglob("__init__.py")):
        if "__pycache__" in init.parts or ".egg-info" in str(init):
            continue
        found.append(".".join(init.parent.relative_to(SRC).parts))
    return found


def _modules(src: Path = SRC) -> dict[str, Path]:
    """``dotted name -> file`` of every module under ``src`` (a package by its name)."""
    out = {}
    for path in sorted(src.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def test_the_training_package_holds_packages_only():
    top = sorted(p.name for p in (SRC / "resireg_train").glob("*.py"))
    assert top == ["__init__.py"], top


#: Packages created by two branches at once (issue 52), whose ``__init__`` is one fixed line so
#: that they merge: what may import them is their floor in the import contract alone
#: (``test_every_training_package_has_its_floor_in_the_import_contract``).
ONE_LINE_INITS = ("resireg_train.checks", "resireg_train.jobs")


@pytest.mark.parametrize("package", _packages())
def test_every_package_says_what_lives_there_and_what_may_import_it(package):
    path = SRC.joinpath(*package.split(".")) / "__init__.py"
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    if package in ONE_LINE_INITS:
        assert path.read_text(encoding="utf-8").count("\n") == 1, f"{package}: one line"
        return
    assert len(doc.split()) >= 15, f"{package}: its docstring says too little: {doc!r}"
    assert "imported by" in doc.lower(), f"{package}: its docstring names no importer"


def test_the_architecture_page_is_short_and_names_every_package():
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) < 300
    missing = [p for p in _packages() if not re.search(rf"`{re.escape(p)}`", text)]
    assert not missing, f"docs/architecture.md does not name {missing}"
    for recipe in ("an encoder", "a variant", "a dataset", "a task", "a metric", "a prior",
                   "a map source", "a text tower", "a distillation teacher", "a report section"):  # fmt: skip
        assert f"### Adding {recipe}\n" in text, recipe


def test_every_training_package_has_its_floor_in_the_import_contract():
    """A new package of resireg_train is placed in the layers of ``[tool.importlinter]``, or
    lint-imports would not check it; ``config`` (the ground) is one layer, the bottom one."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = config["tool"]["importlinter"]["contracts"]
    (layers,) = [
        c["layers"] for c in contracts if c["name"].startswith("Layers inside resireg_train")
    ]
    placed = {m.strip() for layer in layers for m in re.split(r"[|:]", layer)}
    top = {f"resireg_train.{p.name}" for p in (SRC / "resireg_train").iterdir()
           if (p / "__init__.py").is_file()}  # fmt: skip
    assert top <= placed, sorted(top - placed)
    assert layers[-1] == "resireg_train.config", layers[-1]


def _imports(modules: dict[str, Path]) -> dict[str, set[str]]:
    """``module -> the modules of the checkout it imports`` (every import statement, inside
    functions too; a name imported from a package that is a module of its own counts as it;
    importing a submodule runs its parent packages' ``__init__`` too)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                dotted = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                dotted = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                          for a in node.names]  # fmt: skip
            else:
                continue
            for target in dotted:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                while target:  # the module and the packages above it (their __init__ runs)
                    if target != name and not name.startswith(f"{target}."):
                        targets.add(target)
                    target = target.rpartition(".")[0]
        graph[name] = targets
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm, written out
    so the test needs no graph library)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    groups: list[list[str]] = []
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def test_no_import_circle_counting_imports_inside_functions():
    assert _circles(_imports(_modules())) == []


def test_the_circle_check_finds_a_circle_through_a_function(tmp_path):
    """The check can fail: two modules that import each other, one inside a function, and a
    module importing a sibling whose package imports it back, are circles; a chain is not."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg import b\n")
    (pkg / "b.py").write_text("def f():\n    from pkg.a import x\n")
    (pkg / "c.py").write_text("import pkg.sub.d\n")
    (pkg / "sub" / "__init__.py").write_text("from pkg import c\n")
    (pkg / "sub" / "d.py").write_text("")
    (pkg / "e.py").write_text("from pkg import a\n")
    circles = _circles(_imports(_modules(tmp_path)))
    assert sorted(circles) == [["pkg.a", "pkg.b"], ["pkg.c", "pkg.sub"]]
