"""The import layers (``[tool.importlinter]`` in pyproject.toml), checked with import-linter's
``lint-imports``: ``resireg`` never imports ``resireg_train``, Lightning, Hydra or
``datasets``, and inside ``resireg`` and inside ``resireg_train`` every import points down the
layer list (``resireg.specs`` imports nothing of ``resireg`` but :mod:`resireg.errors`; the
run records sit below the evaluation and the search, the CLIs on top). Anyone can run
``lint-imports`` in the checkout for the same report."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from helpers.paths import ROOT

LINT = Path(sys.executable).with_name("lint-imports")


def _lint(src: Path, config: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(src)}
    return subprocess.run([str(LINT), "--config", str(config), "--no-cache"], cwd=config.parent,
                          capture_output=True, text=True, env=env, timeout=300)  # fmt: skip


def test_every_import_contract_is_kept():
    out = _lint(ROOT / "src", ROOT / "pyproject.toml")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Contracts: 3 kept, 0 broken." in out.stdout


def test_the_layer_contract_sees_an_upward_import(tmp_path):
    """The check can fail: a copy of the packages where the ground floor imports the method,
    the library imports the training package, the run records import the evaluation and the
    config ground imports a command's check (inside functions: counted too), breaks the three
    contracts, each naming the import."""
    src = tmp_path / "src"
    for package in ("resireg", "resireg_train"):
        shutil.copytree(ROOT / "src" / package, src / package,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    rules = src / "resireg" / "specs" / "rules.py"
    rules.write_text(rules.read_text() + "\nfrom resireg.method.full import ReSiRegFull\n")
    checks = src / "resireg" / "method" / "checks.py"
    checks.write_text(checks.read_text() + "\nimport resireg_train.record.run_record\n")
    record = src / "resireg_train" / "record" / "run_record.py"
    record.write_text(record.read_text() + "\n\ndef _engine():\n"
                      "    from resireg_train.evaluation import engine\n\n    return engine\n")  # fmt: skip
    # the ground (config/) reaching up into a command's check: config is the bottom floor
    moves = src / "resireg_train" / "config" / "moves.py"
    moves.write_text(moves.read_text() + "\n\ndef _check():\n"
                     "    from resireg_train.checks import train\n\n    return train\n")  # fmt: skip
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    out = _lint(src, tmp_path / "pyproject.toml")
    assert out.returncode == 1
    assert "Contracts: 0 kept, 3 broken." in out.stdout
    assert "resireg_train.record.run_record -> resireg_train.evaluation.engine" in out.stdout
    assert "resireg.specs.rules -> resireg.method.full" in out.stdout
    assert "resireg.method.checks -> resireg_train.record.run_record" in out.stdout


@pytest.mark.parametrize("module", ["resireg.specs", "resireg.errors", "resireg.network"])
def test_the_ground_floor_loads_without_torch(module):
    code = f"import sys, {module}; print(sorted(m for m in ('torch', 'numpy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


PACKAGES = ("resireg", "resireg_train")


def _ours(dotted: str) -> bool:
    return any(dotted == p or dotted.startswith(f"{p}.") for p in PACKAGES)


def _private_imports(path, module: str, root) -> list[str]:
    """``module``'s (its file ``path``) uses of another module's private name, of either
    package: ``from resireg.x import _name`` (relative imports resolved) or ``x._name`` where
    ``x`` is bound to one of their modules (``import resireg.x as x``, ``from resireg import
    x``)."""
    import ast

    def is_module(dotted: str) -> bool:
        parts = dotted.split(".")
        return (root / "/".join(parts)).with_suffix(".py").is_file() or (
            root / "/".join(parts) / "__init__.py"
        ).is_file()

    def private(name: str) -> bool:
        return name.startswith("_") and not name.startswith("__")

    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    bound: dict[str, str] = {}  # local name -> resireg module
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            if not _ours(base):
                continue
            for alias in node.names:
                if private(alias.name) and base != module:
                    found.append(f"{module}:{node.lineno}: from {base} import {alias.name}")
                elif is_module(f"{base}.{alias.name}"):
                    bound[alias.asname or alias.name] = f"{base}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if _ours(alias.name):
                    top = alias.name.split(".")[0]
                    bound[alias.asname or top] = alias.name if alias.asname else top
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in bound:
                target = ".".join([bound[value.id], *reversed(chain)])
                if is_module(target) and target != module:
                    found.append(f"{module}:{node.lineno}: {target}.{node.attr}")
    return found


def test_no_module_uses_another_ones_private_names(tmp_path):
    """Helpers one module needs from another are public (resireg.method.checks' check_variant_inputs,
    resireg.mapping.keys, resireg_train.cli.search.quiet_optuna, ...): an AST scan of src/resireg
    and src/resireg_train finds no import or attribute use of another module's private name.
    The scanner itself is checked on planted uses."""
    root = ROOT / "src"
    files = sorted(path for p in PACKAGES for path in (root / p).rglob("*.py"))
    modules = {}
    for path in files:
        name = ".".join(path.relative_to(root).with_suffix("").parts)
        modules[name.removesuffix(".__init__")] = path
    assert {"resireg.method.pca", "resireg.mapping.keys", "resireg_train.cli.search"} <= set(
        modules
    )
    found = [hit for name, path in modules.items() for hit in _private_imports(path, name, root)]
    assert found == []

    planted = tmp_path / "resireg" / "mapping" / "planted.py"
    planted.parent.mkdir(parents=True)
    for name in ("keys", "voxels"):
        (planted.parent / f"{name}.py").write_text("")
    for name in ("resireg/method/kmeans", "resireg_train/cli/search",
                 "resireg_train/evaluation/engine"):  # fmt: skip
        (tmp_path / f"{name}.py").parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f"{name}.py").write_text("")
    planted.write_text(
        "from resireg_train.cli.search import _optuna\nimport resireg_train.evaluation.engine as eng\n"
        "eng._no_timer\nimport resireg_train\nresireg_train.evaluation.engine._no_timer\n"
        "import resireg.method.kmeans as km\nimport resireg.mapping.voxels\n"
        "from resireg.method.kmeans import _lloyd, kmeans\nfrom .keys import _OFFSET, pack_keys\n"
        "from resireg.mapping import voxels\n"
        "km._tolerance(1)\nresireg.mapping.voxels._check(1)\nvoxels._x\n"
        "from torch import _C\nkm.kmeans\nself._private\n"
    )
    hits = _private_imports(planted, "resireg.mapping.planted", tmp_path)
    assert sorted(hit.split(": ", 1)[1] for hit in hits) == [
        "from resireg.mapping.keys import _OFFSET",
        "from resireg.method.kmeans import _lloyd",
        "from resireg_train.cli.search import _optuna",
        "resireg.mapping.voxels._check",
        "resireg.mapping.voxels._x",
        "resireg.method.kmeans._tolerance",
        "resireg_train.evaluation.engine._no_timer",
        "resireg_train.evaluation.engine._no_timer",
    ]


_CIRCLES = """
import json, sys
import grimp

graph = grimp.build_graph(sys.argv[1], cache_dir=None)
print(json.dumps([
    [module, *chain]
    for module in sorted(graph.modules)
    for imported in sorted(graph.find_modules_directly_imported_by(module))
    if (chain := graph.find_shortest_chain(importer=imported, imported=module))
]))
"""


def _import_circles(src: Path, package: str) -> list[tuple[str, ...]]:
    """Every import circle of ``package`` under ``src`` (grimp, import-linter's graph: imports
    inside functions count too), each as the chain from a module back to itself; in a fresh
    process, so ``src``'s copy is the one scanned, not the package this process imported."""
    import json

    env = {**os.environ, "PYTHONPATH": str(src)}
    out = subprocess.run([sys.executable, "-c", _CIRCLES, package], capture_output=True,
                         text=True, env=env, timeout=300, check=True)  # fmt: skip
    return [tuple(chain) for chain in json.loads(out.stdout)]


def test_resireg_has_no_import_circle_counting_imports_inside_functions(tmp_path):
    """Issue 45: ``models/vlm/card.py`` and ``models/vlm/model.py`` imported each other inside
    functions; both now read exports through ``models/vlm/folder.py``. The scan can fail: a
    copy where the card imports the model inside a function again has that circle."""
    assert _import_circles(ROOT / "src", "resireg") == []

    src = tmp_path / "src"
    shutil.copytree(ROOT / "src" / "resireg", src / "resireg",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    card = src / "resireg" / "models" / "vlm" / "card.py"
    card.write_text(
        card.read_text() + "\n\ndef _late():\n    from resireg.models.vlm import model\n"
    )
    found = _import_circles(src, "resireg")
    assert (
        "resireg.models.vlm.card",
        "resireg.models.vlm.model",
        "resireg.models.vlm.card",
    ) in found
