"""The import layers (``[tool.importlinter]`` in pyproject.toml), checked with import-linter's
``lint-imports``: ``resireg`` never imports ``resireg_train``, Lightning, Hydra or
``datasets``, and inside ``resireg`` every import points down the layer list (``resireg.specs``
imports nothing of ``resireg`` but :mod:`resireg.errors`). Anyone can run ``lint-imports`` in
the checkout for the same report."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(src: Path, config: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(src)}
    return subprocess.run([str(LINT), "--config", str(config), "--no-cache"], cwd=config.parent,
                          capture_output=True, text=True, env=env, timeout=300)  # fmt: skip


def test_every_import_contract_is_kept():
    out = _lint(ROOT / "src", ROOT / "pyproject.toml")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Contracts: 2 kept, 0 broken." in out.stdout


def test_the_layer_contract_sees_an_upward_import(tmp_path):
    """The check can fail: a copy of the packages where the ground floor imports the method,
    and the library imports the training package, breaks both contracts, each naming the
    import."""
    src = tmp_path / "src"
    for package in ("resireg", "resireg_train"):
        shutil.copytree(ROOT / "src" / package, src / package,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    rules = src / "resireg" / "specs" / "rules.py"
    rules.write_text(rules.read_text() + "\nfrom resireg.reconstruct import ReSiRegFull\n")
    checks = src / "resireg" / "checks.py"
    checks.write_text(checks.read_text() + "\nimport resireg_train.results\n")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    out = _lint(src, tmp_path / "pyproject.toml")
    assert out.returncode == 1
    assert "Contracts: 0 kept, 2 broken." in out.stdout
    assert "resireg.specs.rules -> resireg.reconstruct" in out.stdout
    assert "resireg.checks -> resireg_train.results" in out.stdout


@pytest.mark.parametrize("module", ["resireg.specs", "resireg.errors"])
def test_the_ground_floor_loads_without_torch(module):
    code = f"import sys, {module}; print(sorted(m for m in ('torch', 'numpy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
