"""Run folders written by the release before the house v2 (tests/data/runs_before_house_v2: a
training, an evaluation, a map and a search) still resume and rerun after the modules moved and
the keys were renamed: their stored configs name the old class paths and the old spellings
(``logger=csv``, ``configuration=full``), which the moves tables map
(``resireg_train.config.moves``)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import optuna
import pytest
import yaml

from helpers.paths import TESTS
from helpers.run import run
from resireg_train.config.paths import CONFIG_DIR

FIXTURE = TESTS / "data" / "runs_before_house_v2"
TEXT = {".yaml", ".json", ".journal", ".csv", ".log", ".md"}

pytestmark = pytest.mark.slow


@pytest.fixture
def old_runs(tmp_path, tiny_export):
    """A copy of the four folders with their machine paths filled in (the tiny export of the
    session, the demo room bag written again here, this checkout)."""
    from resireg_train.data.room_bag import room_frames, write_bag

    root = tmp_path / "old"
    shutil.copytree(FIXTURE, root)
    bag = write_bag(tmp_path / "room", room_frames(4))
    fill = {"@EXPORT@": str(tiny_export), "@BAG@": str(bag), "@ROOT@": str(root),
            "@CHECKOUT@": str(CONFIG_DIR.parent)}  # fmt: skip
    for path in root.rglob("*"):
        if path.is_file() and path.suffix in TEXT:
            text = path.read_text()
            for key, value in fill.items():
                text = text.replace(key, value)
            path.write_text(text)
    # map.json's record_sha256 covers the paths just filled in: sealed again as its writer
    # seals it (SHA-256 of the canonical JSON without that field), as if written here
    record = json.loads((root / "map" / "map" / "map.json").read_text())
    body = {k: v for k, v in record.items() if k != "record_sha256"}
    record["record_sha256"] = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    (root / "map" / "map" / "map.json").write_text(json.dumps(record, indent=2))
    return root


def _overrides(folder: Path) -> list[str]:
    return yaml.safe_load((folder / ".hydra" / "overrides.yaml").read_text())


def _verdict(proc) -> str:
    return next(line for line in proc.stdout.splitlines() if line.startswith("verdict: "))


def _rerun(folder: Path, out: Path, *overrides: str):
    proc = run("resireg-runs", "rerun", folder, *overrides, "--out", out, "--allow-drift",
               check=False, threads=1)  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _final(folder: Path) -> dict:
    return json.loads((folder / "results.json").read_text())["final"]


def test_an_old_training_resumes_and_reruns(old_runs, tmp_path):
    train = old_runs / "train"
    assert "logger=csv" in _overrides(train)
    proc = run("resireg-train", *_overrides(train), "ckpt_path=last", f"hydra.run.dir={train}",
               threads=1)  # fmt: skip
    assert "Restored all states from the checkpoint" in proc.stdout + proc.stderr
    # a recorded deletion is run again only when given again (resireg-runs rerun's rule)
    again = _rerun(train, tmp_path / "train2", "~callbacks.progress_bar")
    assert _verdict(again).startswith("verdict: identical"), again.stdout[-2000:]
    assert _final(tmp_path / "train2") == _final(train)


def test_an_old_evaluation_reruns_identical(old_runs, tmp_path):
    proc = _rerun(old_runs / "eval", tmp_path / "eval2")
    assert _verdict(proc).startswith("verdict: identical"), proc.stdout[-2000:]
    assert _final(tmp_path / "eval2") == _final(old_runs / "eval") and _final(old_runs / "eval")


def test_an_old_map_resumes_and_reruns(old_runs, tmp_path):
    mapped = old_runs / "map"
    assert "configuration=full" in _overrides(mapped)
    again = _rerun(mapped, tmp_path / "map2")  # before the resume, which records its own run
    assert _verdict(again).startswith("verdict: identical"), again.stdout[-2000:]
    frames = json.loads((mapped / "map" / "map.json").read_text())["frames"]
    proc = run("resireg-map", *_overrides(mapped), "resume=true", f"hydra.run.dir={mapped}",
               threads=1)  # fmt: skip
    said = proc.stdout + proc.stderr
    assert f"resuming {mapped / 'map'}: {frames} frames" in said, said[-2000:]


def test_an_old_search_resumes(old_runs):
    search = old_runs / "search"
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(search / "optuna.journal")))
    (before,) = optuna.get_all_study_summaries(storage)
    assert before.n_trials == 2
    run("resireg-train", "experiment=smoke", "hparams_search=stage1_optuna",
        "hparams_search.n_trials=3", "trainer.max_epochs=1", "data.steps_per_epoch=2",
        f"hydra.sweep.dir={search}", "-m", threads=1)  # fmt: skip
    study = optuna.load_study(study_name=before.study_name, storage=storage)
    states = [t.state for t in study.get_trials()]
    assert states == [optuna.trial.TrialState.COMPLETE] * 3, states
