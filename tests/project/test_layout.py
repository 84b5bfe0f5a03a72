"""The layout by role stays as docs/architecture.md draws it: ``resireg_train``'s top level holds
packages only, every package's docstring says what may import it, the architecture page stays
short and names every package, every package of ``resireg_train`` has its floor in the import
contract, no module imports itself back through others (imports inside functions
counted), every component table is a ``<THING>_SPECS`` of a ``specs`` module, every module
over 500 lines says why it is one idea, and ``tests/`` mirrors the packages (issue 53): no test
file directly under ``tests/``, every test folder a package of ``src/`` (or ``project/``), the
shared helpers only in ``tests/helpers/``, every test file's name unique."""

from __future__ import annotations

import ast
import re
import sys
from collections import Counter
from pathlib import Path

import pytest

from helpers.paths import ROOT, TESTS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pytest's own dependency before Python 3.11
    import tomli as tomllib

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


# ------------------------------------------------------------------ one naming pattern for tables
#: A component table is a ``SpecTable`` named ``<THING>_SPECS`` in a module named ``specs.py``
#: or in a ``specs`` package (``resireg/specs/``) (docs/architecture.md#spec-tables), so one search finds them all.
_TABLE_NAME = re.compile(r"[A-Z][A-Z0-9]*(_[A-Z0-9]+)*_SPECS")


def _names_spec_table(node: ast.expr | None) -> bool:
    """``SpecTable``, ``x.SpecTable`` or ``SpecTable[...]`` (a call's callee or an annotation)."""
    if isinstance(node, ast.Subscript):
        node = node.value
    return (isinstance(node, ast.Name) and node.id == "SpecTable") or (
        isinstance(node, ast.Attribute) and node.attr == "SpecTable"
    )


def _spec_tables(src: Path = SRC) -> dict[str, list[str]]:
    """``module -> the names it binds, at module level, to a SpecTable``: assigned a
    ``SpecTable(...)`` call or annotated ``SpecTable[...]``."""
    found: dict[str, list[str]] = {}
    for module, path in _modules(src).items():
        text = path.read_text(encoding="utf-8")
        if "SpecTable" not in text:
            continue
        for node in ast.parse(text).body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                targets, value, note = [node.target], node.value, node.annotation
            elif isinstance(node, ast.Assign):
                targets, value, note = node.targets, node.value, None
            else:
                continue
            call = isinstance(value, ast.Call) and _names_spec_table(value.func)
            if call or _names_spec_table(note):
                found.setdefault(module, []).extend(
                    t.id for t in targets if isinstance(t, ast.Name)
                )
    return found


def _table_problems(tables: dict[str, list[str]]) -> list[str]:
    """``module.NAME`` of every table off the pattern (its name or its module)."""
    return sorted(
        f"{module}.{name}"
        for module, names in tables.items()
        for name in names
        if not _TABLE_NAME.fullmatch(name)
        or "specs" not in module.split(".")  # specs.py, or a module of a specs package
    )


def test_every_component_table_is_a_spec_table_named_specs_in_a_specs_module():
    """Issue 52 item 4: every SpecTable of both packages (found by an AST scan of src/, then
    imported) is a ``<THING>_SPECS`` of a ``specs`` module; a table named otherwise fails."""
    import importlib

    from resireg.specs.table import SpecTable

    tables = _spec_tables()
    flat = {f"{m}.{n}" for m, names in tables.items() for n in names}
    assert {  # the scan finds the tables of both packages (it is not vacuous)
        "resireg.specs.encoders.ENCODER_SPECS", "resireg.specs.variants.VARIANT_SPECS",
        "resireg_train.data.specs.DATASET_SPECS", "resireg_train.evaluation.specs.TASK_SPECS",
        "resireg_train.training.specs.TEACHER_SPECS", "resireg_train.report.specs.SECTION_SPECS",
    } <= flat  # fmt: skip
    for module, names in tables.items():
        loaded = importlib.import_module(module)
        for name in names:
            assert isinstance(getattr(loaded, name), SpecTable), f"{module}.{name}"
        # a table the scan did not see (built by a helper) is a module-level SpecTable too
        bound = {n for n, v in vars(loaded).items() if isinstance(v, SpecTable)
                 and getattr(v, "__module__", module) == module}  # fmt: skip
        own = {t.id for node in ast.parse(Path(loaded.__file__).read_text(encoding="utf-8")).body
               for t in getattr(node, "targets", [getattr(node, "target", None)])
               if isinstance(t, ast.Name)}  # fmt: skip
        assert bound & own <= set(names), f"{module}: tables {sorted(bound & own - set(names))}"
    assert sorted(_table_problems(tables)) == []


def test_the_table_check_fails_on_a_table_named_otherwise(tmp_path):
    """The check can fail: a table under another name, or in a module not named ``specs``, is
    reported; ``<THING>_SPECS`` in ``specs.py`` (plain or annotated) is not."""
    pkg = tmp_path / "pkg"
    (pkg / "specs").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "specs" / "__init__.py").write_text("")
    (pkg / "sections.py").write_text(
        "from t import SpecTable\nREPORT_SECTIONS = SpecTable('s', [])\n"
    )
    (pkg / "report.py").write_text("import t\nSECTION_SPECS = t.SpecTable('s', [])\n")
    (pkg / "specs" / "text.py").write_text("sections: SpecTable[int] = make()\n")
    (pkg / "specs" / "good.py").write_text("GOOD_SPECS: SpecTable[int] = SpecTable('g', [])\n")
    (pkg / "specs.py").write_text("OTHER_SPECS = SpecTable('o', [])\nNOT_A_TABLE = dict()\n")
    tables = _spec_tables(tmp_path)
    assert tables == {"pkg.sections": ["REPORT_SECTIONS"], "pkg.report": ["SECTION_SPECS"],
                      "pkg.specs.text": ["sections"], "pkg.specs.good": ["GOOD_SPECS"],
                      "pkg.specs": ["OTHER_SPECS"]}  # fmt: skip
    problems = _table_problems(tables)
    assert problems == ["pkg.report.SECTION_SPECS", "pkg.sections.REPORT_SECTIONS",
                        "pkg.specs.text.sections"]  # fmt: skip


# ------------------------------------------------------------------ files of one idea
#: A module longer than this says in its docstring, in a paragraph starting ``One idea:``, why
#: it is one idea (issue 52 item 5).
LONG_MODULE = 500


def _says_one_idea(doc: str) -> bool:
    """A paragraph of ``doc`` (blank-line separated) starts with ``One idea:``."""
    return any(p.strip().startswith("One idea:") for p in re.split(r"\n[ \t]*\n", doc))


def _long_without_reason(src: Path = SRC) -> list[str]:
    """The modules over :data:`LONG_MODULE` lines whose docstring has no ``One idea:`` paragraph."""
    out = []
    for module, path in _modules(src).items():
        text = path.read_text(encoding="utf-8")
        if len(text.splitlines()) > LONG_MODULE:
            if not _says_one_idea(ast.get_docstring(ast.parse(text)) or ""):
                out.append(module)
    return sorted(out)


def test_every_long_module_says_why_it_is_one_idea():
    assert sorted(_long_without_reason()) == []


def test_the_long_module_check_fails_on_a_new_long_module(tmp_path):
    """The check can fail: a module of 501 lines without the paragraph (or with the words
    inside another paragraph) is reported; 500 lines, or the paragraph, pass."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    body = "x = 1\n"
    (pkg / "__init__.py").write_text("")
    (pkg / "bare.py").write_text('"""Several things."""\n' + body * 500)  # 501 lines
    (pkg / "inline.py").write_text('"""Several things. One idea: no."""\n' + body * 500)
    (pkg / "short.py").write_text('"""Several things."""\n' + body * 499)  # 500 lines
    (pkg / "said.py").write_text('"""Sums.\n\nOne idea: the sums, written once."""\n' + body * 500)
    assert _long_without_reason(tmp_path) == ["pkg.bare", "pkg.inline"]


# ------------------------------------------------------------------ tests/ mirrors the packages
#: The folders of tests/ that mirror no package: the project's own checks and the shared helpers.
TEST_OWN = ("project", "helpers")
#: The folders of tests/ that hold data, not tests (read by the tests, left as they are).
TEST_DATA = ("data", "fixtures", "conf")


def _test_layout_problems(tests: Path = TESTS, src: Path = SRC) -> list[str]:
    """What breaks the mirror in ``tests``: a test file directly under it, a folder that is no
    package of ``src`` (nor ``project/``, ``helpers/`` or a data folder), a Python module outside
    ``helpers/`` that is no test file (the root's ``conftest.py`` excepted), two test files of
    one name (pytest imports each by its name)."""
    problems, names = [], Counter()
    for path in sorted(tests.rglob("*")):
        rel = path.relative_to(tests)
        if rel.parts[0] in TEST_DATA or "__pycache__" in rel.parts or rel.parts[0].startswith("."):
            continue
        if path.is_dir():
            if rel.parts[0] not in TEST_OWN and not (src / rel / "__init__.py").is_file():
                problems.append(f"tests/{rel.as_posix()}/ mirrors no package of src/")
            continue
        if path.suffix != ".py" or rel.parts[0] == "helpers" or rel.as_posix() == "conftest.py":
            continue
        if not path.name.startswith("test_"):
            problems.append(f"tests/{rel.as_posix()}: a helper outside tests/helpers/")
        elif len(rel.parts) == 1:
            problems.append(f"tests/{rel.as_posix()}: a test file directly under tests/")
        else:
            names[path.name] += 1
    problems += [f"{name}: {n} test files of this name" for name, n in names.items() if n > 1]
    return problems


def test_the_tests_mirror_the_packages():
    assert _test_layout_problems() == []


def test_the_mirror_check_fails_on_each_kind_of_misplaced_file(tmp_path):
    """The check can fail: a flat test file, a folder of no package, a helper outside
    ``helpers/`` and a name used twice are each reported; the mirrored, project, helper and
    data files pass."""
    src, tests = tmp_path / "src", tmp_path / "tests"
    for rel in ("pkg/__init__.py", "pkg/sub/__init__.py"):
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text("")
    for rel in ("conftest.py", "pkg/sub/test_a.py", "pkg/test_b.py", "project/test_c.py",
                "helpers/__init__.py", "helpers/run.py", "data/x/make.py", "test_flat.py",
                "pkg/other/test_d.py", "_run.py", "pkg/util.py", "project/test_a.py"):  # fmt: skip
        (tests / rel).parent.mkdir(parents=True, exist_ok=True)
        (tests / rel).write_text("")
    assert _test_layout_problems(tests, src) == [
        "tests/_run.py: a helper outside tests/helpers/",
        "tests/pkg/other/ mirrors no package of src/",
        "tests/pkg/util.py: a helper outside tests/helpers/",
        "tests/test_flat.py: a test file directly under tests/",
        "test_a.py: 2 test files of this name",
    ]
