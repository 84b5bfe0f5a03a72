"""The optional extras install what the encoders' code imports (issue 22, case 14)."""

import importlib
import importlib.metadata
import importlib.util
import sys

import pytest
from hydra import compose, initialize_config_dir
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from helpers.paths import ROOT
from resireg.errors import ConfigError
from resireg_train.config.machine import ENCODER_IMPORTS, check_available
from resireg_train.config.paths import CONFIG_DIR

if sys.version_info >= (3, 11):
    import tomllib
else:  # pytest's own dependency before Python 3.11
    import tomli as tomllib

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
EXTRAS = PYPROJECT["project"]["optional-dependencies"]
LISTED = sorted({n.module for needs in ENCODER_IMPORTS.values() for n in needs})


def _names(requirements):
    """Distribution names of the requirements that apply to this interpreter, this project's
    own extras (``resireg[encoders]``) expanded."""
    names = set()
    for r in map(Requirement, requirements):
        if r.marker is not None and not r.marker.evaluate():
            continue
        if canonicalize_name(r.name) == "resireg":
            names |= set().union(*(_names(EXTRAS[extra]) for extra in r.extras))
        else:
            names.add(canonicalize_name(r.name))
    return names


@pytest.mark.parametrize("module", LISTED)
def test_every_listed_module_imports_in_the_dev_install(module):
    importlib.import_module(module)


def test_the_encoders_extra_and_dev_install_every_listed_module():
    """Each listed module's distribution, as the installed packages' own metadata names it
    (importlib.metadata, independent of the list), is a requirement of the encoders extra,
    which dev includes, or a core dependency (transformers); distutils (stdlib here) is
    setuptools' from Python 3.12 on."""
    providers = importlib.metadata.packages_distributions()
    core = _names(PYPROJECT["project"]["dependencies"])
    encoders, dev = _names(EXTRAS["encoders"]) | core, _names(EXTRAS["dev"]) | core
    for needs in ENCODER_IMPORTS.values():
        for n in needs:
            if n.module in sys.stdlib_module_names:  # distutils before Python 3.12
                assert any(
                    Requirement(r).name == n.dist and "3.12" in str(Requirement(r).marker)
                    for r in EXTRAS["encoders"]
                ), n
                continue
            installed = {canonicalize_name(d) for d in providers[n.module]}
            assert canonicalize_name(n.dist) in installed, (n.module, installed)
            assert canonicalize_name(n.dist) in encoders, n
            assert canonicalize_name(n.dist) in dev, n


def test_a_missing_module_is_named_before_the_encoder_loads(monkeypatch):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        radseg = compose("eval", overrides=["encoder=radseg"])
        clip = compose("eval", overrides=["encoder=radio_v3b_clip"])
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in ("segment_anything", "transformers")
                        else real(name, *a))  # fmt: skip
    with pytest.raises(ConfigError) as err:
        check_available(radseg)
    assert (
        "encoder.kind='radseg': RADSeg hubconf.py, radseg/radseg.py imports segment_anything, "
        'which is not installed: pip install -e ".[encoders]" (or pip install segment-anything)'
    ) in str(err.value)
    assert "NVlabs/RADIO radio/siglip2_adaptor.py" in str(err.value)
    check_available(clip)  # the CLIP adaptor of RADIO does not import transformers


#: Modules resireg.ros2 imports where a ROS 2 install provides them (not on PyPI): the camera
#: pose from tf (resireg.ros2.poses.TfPoses); without them the pose comes from a topic.
FROM_A_ROS_INSTALL = ("tf2_ros",)


def _imported_distributions(package, module_level=True, skip=()):
    """Third-party distributions a package imports, from the source's own AST: its module-level
    imports, or every import (functions' lazy ones too: transformers, sentencepiece, sklearn);
    ``skip``: subpackages left out."""
    import ast

    root = ROOT / "src" / package
    top = set()
    for path in root.rglob("*.py"):
        if path.relative_to(root).parts[0] in skip:
            continue
        tree = ast.parse(path.read_text())
        for node in tree.body if module_level else ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and not node.level else [])  # fmt: skip
            top |= {n.split(".")[0] for n in names if n}
    top -= set(sys.stdlib_module_names) | {"resireg", "resireg_train", "__future__"}
    dists = importlib.metadata.packages_distributions()
    return {module: {canonicalize_name(d) for d in dists.get(module, ())} for module in sorted(top)}


@pytest.mark.slow
def test_the_core_install_is_what_resireg_imports_and_train_carries_the_rest():
    """Issue 23 item 4: `resireg` installs alone (a robot's inference): what its modules import
    at module level is a core dependency, every core dependency is imported by it (torchvision:
    by open_clip's transforms), what it imports lazily is core or an extra; Lightning, Hydra and
    datasets live in the `train` extra, which `dev` includes."""
    core = _names(PYPROJECT["project"]["dependencies"])
    train, dev = _names(EXTRAS["train"]), _names(EXTRAS["dev"])
    for module, dists in _imported_distributions("resireg", skip=("ros2",)).items():
        assert dists & core, f"resireg imports {module} at module level; not a core dependency"
    anywhere = _imported_distributions("resireg", module_level=False)
    needed = set().union(*anywhere.values())
    unused = core - needed
    assert unused <= {"torchvision"}, f"core dependencies resireg never imports: {unused}"
    robot = _installed_with(_names(EXTRAS["robot"]))  # the ROS meta-packages' ros-* wheels
    for module, dists in anywhere.items():
        if module in FROM_A_ROS_INSTALL:
            continue
        assert dists & (core | dev | robot), f"resireg imports {module}; in no extra"
    for module, dists in _imported_distributions("resireg_train").items():
        assert dists & (core | train | dev), f"resireg_train imports {module}; in no extra"
    # the 25M VLM's SigLIP 2 tokenizer is open_clip's HFTokenizer: text queries need it
    assert "transformers" in core
    assert {"lightning", "hydra-core", "datasets"} <= train
    assert not {"lightning", "hydra-core", "datasets"} & core
    assert train <= dev


def _installed_with(names):
    """``names`` and every distribution they require, as installed (importlib.metadata)."""
    from importlib.metadata import PackageNotFoundError, requires

    todo, seen = list(names), set()
    while todo:
        name = canonicalize_name(todo.pop())
        if name in seen:
            continue
        seen.add(name)
        try:
            reqs = requires(name) or []
        except PackageNotFoundError:
            continue
        for r in map(Requirement, reqs):
            if r.marker is None or r.marker.evaluate({"extra": ""}):
                todo.append(r.name)
    return seen


def test_the_live_node_imports_the_core_and_the_robot_extra():
    """resireg.ros2 (the live node, docs/robot.md) imports at module level only the core and
    what the robot extra installs: ROS 2 Jazzy's wheels (rclpy, the message packages; the
    ros-jazzy-* distributions are meta-packages of ros-* ones, expanded as installed)."""
    core, robot = _names(PYPROJECT["project"]["dependencies"]), _names(EXTRAS["robot"])
    if not any(name.startswith("ros-jazzy-") for name in robot):
        pytest.skip("no ROS 2 wheels for this Python / platform (the robot extra's marker)")
    allowed = core | _installed_with(robot)
    root = ROOT / "src" / "resireg"
    for module, dists in _imported_distributions("resireg").items():
        if dists & core:
            continue
        assert dists & allowed, f"resireg.ros2 imports {module}; neither core nor robot extra"
        users = [p for p in root.rglob("*.py") if f"import {module}" in p.read_text()
                 or f"from {module}" in p.read_text()]  # fmt: skip
        assert all("ros2" in p.relative_to(root).parts for p in users), (module, users)
    assert "robot" in {x for r in EXTRAS["dev"] for x in Requirement(r).extras}


def test_resireg_train_names_the_train_extra_when_it_is_missing(monkeypatch):
    """Without the train extra, importing resireg_train says which distributions to install."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "lightning" else real(name, *a))  # fmt: skip
    for name in [m for m in sys.modules if m == "resireg_train"]:
        monkeypatch.delitem(sys.modules, name)
    with pytest.raises(ImportError, match=r"'train' extra \(lightning not installed\).*\[train\]"):
        importlib.import_module("resireg_train")
