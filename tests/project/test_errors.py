"""One error base: every exception class of ``resireg`` and ``resireg_train`` derives from
:class:`resireg.errors.ResiregError`; the library names its own arguments, and
``resireg_train`` adds the config path at its boundary (:func:`resireg_train.config.errors.config_path`)."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import resireg
import resireg_train
from resireg.errors import ConfigError, DataError, MapError, OfflineError, ResiregError

#: Exception classes that may stay outside the base, each with the reason.
OUTSIDE_THE_BASE = {
    # private: raised and caught inside one function, never seen by a caller
    "resireg_train.data.scannet._FrameError": "private: one frame's failure, caught in the module",
    # not an error: optuna's signal that the pruner stopped the trial; code that catches
    # ResiregError (a bad input) must not swallow it
    "resireg_train.search.pruning.TrialPrunedStop": "a control-flow signal, not an error",
    # a warning (an old map format loaded), raised only by warnings.warn: nothing catches it
    "resireg.mapping.map_file.MapFormatWarning": "a warning category, not an error",
}


def _modules(package):
    """Every module of ``package``, imported; those whose optional dependencies are missing
    (ROS 2, open3d, gradio, ...) are left out."""
    found = [package]
    for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
        try:
            found.append(importlib.import_module(info.name))
        except ImportError:  # an optional dependency (ModuleNotFoundError, or a system library)
            continue
    return found


@pytest.fixture(scope="module")
def modules():
    return _modules(resireg) + _modules(resireg_train)


def _exception_classes(module):
    for _, obj in vars(module).items():
        if inspect.isclass(obj) and issubclass(obj, BaseException):
            if obj.__module__ == module.__name__:
                yield obj


def test_every_error_class_derives_from_the_base(modules):
    outside = []
    seen = set()
    for module in modules:
        for cls in _exception_classes(module):
            name = f"{cls.__module__}.{cls.__qualname__}"
            seen.add(name)
            if not issubclass(cls, ResiregError) and name not in OUTSIDE_THE_BASE:
                outside.append(name)
    assert not outside, f"error classes outside resireg.errors.ResiregError: {outside}"
    assert len(seen) > 10  # the walk found the project's classes


def test_each_error_has_its_kind_and_keeps_its_builtin_base():
    from resireg.errors import ConfigError as TrainConfigError
    from resireg.errors import WriteError
    from resireg.integrity import IntegrityError
    from resireg.mapping.fusion import MapFullError
    from resireg.method.checks import NonFiniteError
    from resireg.models.hub import WeightsUnavailableError
    from resireg.specs.table import UnknownNameError
    from resireg_train.evaluation.base import NothingScoredError
    from resireg_train.jobs.run_folder import RunFolderBusy
    from resireg_train.playground.core import PlaygroundError
    from resireg_train.search.journal import JournalError
    from resireg_train.search.loop import SearchError
    from resireg_train.search.workers import SearchRecordError
    from resireg_train.training.checkpoints import CheckpointError, UnsafeCheckpointError

    assert TrainConfigError is ConfigError  # one class, re-exported where it always was
    assert IntegrityError is importlib.import_module("resireg.errors").IntegrityError
    kinds = {
        WeightsUnavailableError: (OfflineError, RuntimeError),
        MapFullError: (MapError, RuntimeError),
        NonFiniteError: (DataError, ValueError),
        IntegrityError: (DataError, ValueError),
        PlaygroundError: (ConfigError, ValueError),
        UnknownNameError: (ConfigError, KeyError),
        CheckpointError: (ResiregError, RuntimeError),
        UnsafeCheckpointError: (ResiregError, __import__("pickle").UnpicklingError),
        SearchError: (ResiregError, RuntimeError),
        SearchRecordError: (ResiregError, ValueError),
        JournalError: (DataError, ValueError),
        WriteError: (ResiregError, OSError),
        RunFolderBusy: (ResiregError, RuntimeError),
        NothingScoredError: (ResiregError, RuntimeError),
    }
    for cls, bases in kinds.items():
        assert issubclass(cls, bases), (cls, bases)


# ---------------------------------------------------------------- no config keys in resireg
#: Packages of resireg whose functions the key-parameter check leaves out, each with the reason.
KEYS_KEPT = {
    "resireg.sources": "the map sources: their own branch removes its keys",
    "resireg.specs": "the spec tables: their own branch",
}


def _signatures(module):
    """``(qualified name, signature)`` of the functions and classes ``module`` defines (and of
    the classes' methods)."""
    for name, obj in vars(module).items():
        if getattr(obj, "__module__", None) != module.__name__:
            continue
        found = []
        if inspect.isclass(obj):
            found.append((name, obj))
            for attr, member in vars(obj).items():
                member = getattr(member, "__func__", member)  # static and class methods
                if inspect.isfunction(member):
                    found.append((f"{name}.{attr}", member))
        elif inspect.isfunction(obj):
            found.append((name, obj))
        for qualname, function in found:
            try:
                yield qualname, inspect.signature(function)
            except (TypeError, ValueError):  # no signature to read
                continue


def test_resireg_takes_no_config_key(modules):
    """The library names its own arguments in its errors; no function of it takes a config key
    to put in its messages (``resireg_train`` adds the config path: ``config_path``)."""
    checked, found = 0, []
    for module in modules:
        name = module.__name__
        if not (name == "resireg" or name.startswith("resireg.")):
            continue
        if any(name == kept or name.startswith(f"{kept}.") for kept in KEYS_KEPT):
            continue
        for qualname, signature in _signatures(module):
            checked += 1
            bad = {"key", "config_key"} & set(signature.parameters)
            if bad:
                found.append(f"{name}.{qualname}: {sorted(bad)}")
    assert not found, found
    assert checked > 200  # the walk read the library's signatures


# ---------------------------------------------------------------- naming arguments
def _raise_in_resireg(err, module="resireg.fake"):
    """A function raising ``err`` from code of ``module`` (its innermost frame's module): of
    ``resireg``, as the library's own errors are."""
    namespace = {"__name__": module, "err": err}
    exec("def fail():\n    raise err\n", namespace)
    return namespace["fail"]


def test_rename_arguments_renames_mentions_not_words_paths_or_dotted_names():
    from resireg.errors import rename_arguments

    names = {"repo": "encoder.repo", "weights": "encoder.weights", "clip": "encoder.clip"}
    message = (
        "RADIO needs github.com. Pass repo=/x/RADIO (text_weights=, model.repo=, 'repo=1', "
        "/a/repo=2) or clip.weights=/w; the weights are not cached"
    )
    renamed, starts = rename_arguments(message, names)
    assert not starts
    assert renamed == (
        "RADIO needs github.com. Pass encoder.repo=/x/RADIO (text_weights=, model.repo=, "
        "'repo=1', /a/repo=2) or encoder.clip.weights=/w; the weights are not cached"
    )
    for message, expected in [
        ("weights is not set.", "encoder.weights is not set."),
        ("repo: no such folder", "encoder.repo: no such folder"),
        ("clip.weights='x': no such file", "encoder.clip.weights='x': no such file"),
        ("repo='a' names a ref", "encoder.repo='a' names a ref"),
    ]:
        assert rename_arguments(message, names) == (expected, True)
    assert rename_arguments("repos=2", names) == ("repos=2", False)
    assert rename_arguments("names=['x']: unknown", {"names": "variants"}) == (
        "variants=['x']: unknown",
        True,
    )


def test_config_path_names_the_config_key_at_the_boundary():
    from resireg.models.hub import WeightsUnavailableError
    from resireg_train.config.errors import config_path

    # a message about an argument's value: a ConfigError, still of its own type
    with pytest.raises(FileNotFoundError) as err:
        with config_path("encoder", ("repo", "source")):
            _raise_in_resireg(FileNotFoundError("repo='/x': no such directory"))()
    assert isinstance(err.value, ConfigError)
    assert str(err.value) == "encoder.repo='/x': no such directory"
    assert type(err.value).__name__ == "FileNotFoundError"  # shown as the library's error
    # a hint that names an argument: renamed, its type kept
    offline = WeightsUnavailableError("RADIO needs github.com. Pass repo=/path/to/RADIO")
    with pytest.raises(WeightsUnavailableError) as err:
        with config_path("model.teacher", ("repo",)):
            _raise_in_resireg(offline)()
    assert not isinstance(err.value, ConfigError)
    assert str(err.value) == "RADIO needs github.com. Pass model.teacher.repo=/path/to/RADIO"
    # a plain ValueError naming an argument: a ConfigError
    with pytest.raises(ConfigError, match=r"^variants=\['x'\]: unknown"):
        with config_path("variants", {"names": "variants"}):
            _raise_in_resireg(ValueError("names=['x']: unknown"))()
    # naming no argument (or raised elsewhere): the same error, with the config path as a note
    for error in (ValueError("n_prototypes must be positive"), RuntimeError("CUDA error")):
        with pytest.raises(type(error)) as err:
            with config_path("encoder", ("repo",)):
                _raise_in_resireg(error)()
        assert err.value is error and error.__notes__ == ["config: encoder"]
    third_party = ValueError("repo=1: from someone else's code")
    with pytest.raises(ValueError) as err:
        with config_path("encoder", ("repo",)):
            raise third_party
    assert err.value is third_party and str(third_party).startswith("repo=1")
    assert third_party.__notes__ == ["config: encoder"]
    # resireg_train's own errors name their config paths already: untouched
    own = ConfigError("encoder.kind='x': expected one of [...]")
    with pytest.raises(ConfigError) as err:
        with config_path("encoder", ("kind",)):
            _raise_in_resireg(own, "resireg_train.fake")()
    assert err.value is own and not getattr(own, "__notes__", None)


def test_a_wrapping_library_function_names_its_own_argument():
    """``arguments_under``: OtasEncoder passes its ``clip`` on to ClipEncoder, whose errors
    then name ``clip.weights``; resireg_train adds ``encoder.`` to that."""
    from resireg.errors import arguments_under
    from resireg_train.config.errors import config_path

    with pytest.raises(ConfigError) as err:
        with config_path("encoder", ("clip",)):
            with arguments_under("clip", ("weights",)):
                _raise_in_resireg(ValueError("weights='x': no such file"))()
    assert str(err.value) == "encoder.clip.weights='x': no such file"


def test_the_cli_error_text_carries_the_notes():
    from resireg_train.config.errors import error_message
    from resireg_train.jobs.console import error_text

    err = RuntimeError("CUDA error: out of memory")
    err.__notes__ = ["config: encoder"]
    assert error_text(err) == "RuntimeError: CUDA error: out of memory\nconfig: encoder"
    assert error_message(err) == "CUDA error: out of memory\nconfig: encoder"


def test_a_renamed_error_pickles_as_the_librarys_class():
    import pickle

    from resireg_train.config.errors import config_path

    with pytest.raises(FileNotFoundError) as err:
        with config_path("encoder", ("repo",)):
            _raise_in_resireg(FileNotFoundError("repo='/x': no such directory"))()
    back = pickle.loads(pickle.dumps(err.value))
    assert type(back) is FileNotFoundError and str(back) == str(err.value)


def test_resireg_eval_names_the_encoder_key_of_a_library_error(tmp_path):
    """The library says ``weights='...'``; resireg-eval's failed record says
    ``encoder.weights='...'`` (no model is built: the tag check fails first)."""
    import json

    from hydra import compose, initialize_config_dir

    from resireg_train.cli.eval import evaluate
    from resireg_train.config.paths import CONFIG_DIR

    weights = str(tmp_path / "absent.bin")
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", ["encoder=clip_vit_b16", f"encoder.weights={weights}",
                               "dataset=synthetic", f"paths.output_dir={tmp_path}"])  # fmt: skip
    with pytest.raises(ConfigError, match=rf"^encoder\.weights='{weights}' is neither"):
        evaluate(cfg)
    record = json.loads((tmp_path / "results.json").read_text())
    assert record["status"] == "failed"
    assert f"ConfigError: encoder.weights='{weights}' is neither" in record["error"]
