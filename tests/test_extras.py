"""The optional extras install what the encoders' code imports (issue 22, case 14)."""

import importlib
import importlib.metadata
import importlib.util
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from resireg_train.cli.task import CONFIG_DIR
from resireg_train.validation import ENCODER_IMPORTS, ConfigError, check_available

if sys.version_info >= (3, 11):
    import tomllib
else:  # pytest's own dependency before Python 3.11
    import tomli as tomllib

PYPROJECT = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
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
    which dev includes; distutils (stdlib here) is setuptools' from Python 3.12 on."""
    providers = importlib.metadata.packages_distributions()
    encoders, dev = _names(EXTRAS["encoders"]), _names(EXTRAS["dev"])
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
