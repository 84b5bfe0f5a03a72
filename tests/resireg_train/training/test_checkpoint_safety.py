"""Checkpoints are read weights-only: a pickle that would run code is refused before it runs.

``ckpt_path=`` and ``model.init_from=`` were read with ``torch.load(weights_only=False)``, so a
crafted checkpoint created a file through its pickle before the run failed. The file here
would do the same (its control test shows it: a plain ``weights_only=False`` load creates the
marker); every path of the project must refuse it, naming the file and the global, and leave
no marker.
"""

from __future__ import annotations

import pathlib
import pickle

import pytest
import torch
from hydra import compose, initialize_config_dir

from resireg_train.cli.train import train
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.jobs.train import build
from resireg_train.training.checkpoints import (
    AtomicCheckpointIO,
    CheckpointError,
    UnsafeCheckpointError,
    read_checkpoint,
    resolve_checkpoint,
)


class _Touch:
    """Unpickling this calls ``Path.touch(marker)``: a stand-in for any code a pickle runs."""

    def __init__(self, marker: pathlib.Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def _malicious(tmp_path: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path]:
    """A Lightning-looking checkpoint (global_step, state_dict) with the payload inside."""
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.ckpt"
    torch.save({"global_step": 3, "state_dict": {"vlm.head.x": torch.zeros(1)},
                "payload": _Touch(marker)}, path)  # fmt: skip
    return path, marker


def _compose(*overrides):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=list(overrides))


def test_the_payload_runs_under_a_plain_unsafe_load(tmp_path):
    """Control: the file really is malicious (so the refusals below mean something)."""
    path, marker = _malicious(tmp_path)
    torch.load(path, weights_only=False)
    assert marker.exists()


def test_ckpt_path_refuses_a_pickle_that_would_run_code(tmp_path):
    path, marker = _malicious(tmp_path)
    problem = read_checkpoint(path)
    assert isinstance(problem, str) and "not weights (global getattr)" in problem
    with pytest.raises(CheckpointError, match=r"ckpt_path=.*evil\.ckpt.*cannot be read .*getattr"):
        resolve_checkpoint(str(path), tmp_path)
    with pytest.raises(UnsafeCheckpointError, match=r"evil\.ckpt.*global getattr"):
        AtomicCheckpointIO().load_checkpoint(path)  # what Lightning's restore calls
    # ckpt_path=last falls back past the unsafe last.ckpt, and says why when none is left
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    path.rename(tmp_path / "run" / "checkpoints" / "last.ckpt")
    with pytest.raises(CheckpointError, match=r"last\.ckpt .*global getattr"):
        resolve_checkpoint("last", tmp_path / "run")
    assert not marker.exists()


def test_model_init_from_refuses_a_pickle_that_would_run_code(tmp_path):
    path, marker = _malicious(tmp_path)
    module, _ = build(_compose("experiment=smoke", f"paths.output_dir={tmp_path / 'run'}"))
    with pytest.raises(pickle.UnpicklingError, match=r"model\.init_from=.*evil\.ckpt.*getattr"):
        module.load_trained(path)
    assert not marker.exists()


def test_the_training_entry_point_refuses_both_before_any_step(tmp_path):
    path, marker = _malicious(tmp_path)
    common = ("experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=1",
              "~callbacks.progress_bar")  # fmt: skip
    with pytest.raises(CheckpointError, match="global getattr"):
        train(_compose(*common, f"paths.output_dir={tmp_path / 'a'}", f"ckpt_path={path}"))
    with pytest.raises(UnsafeCheckpointError, match="model.init_from"):
        train(_compose(*common, f"paths.output_dir={tmp_path / 'b'}", f"+model.init_from={path}"))
    assert not marker.exists()
    assert not (tmp_path / "a" / "checkpoints").exists()
