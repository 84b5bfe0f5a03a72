"""Renamed config keys (issue 52: ``logger`` -> ``tracker``, map.yaml's ``rerun`` -> ``viewer``)
keep their old spelling for one release, through the one table beside the moved class paths
(:mod:`resireg_train.config.moves`): a command typed in the old spelling runs with one warning
line naming the new key and records the new key; both spellings together are refused in one
line naming both; a stored run folder in the old spelling resumes and reruns silently; one
naming a class of ours that is gone and in no table is refused naming it and the release."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import yaml

from helpers.paths import TESTS
from helpers.run import run
from resireg.errors import ConfigError
from resireg_train.config import moves
from resireg_train.config.moves import (
    MOVED_TARGETS,
    RENAMED_KEYS,
    check_stored_targets,
    current_argv,
    current_overrides,
    current_spelling,
)
from resireg_train.config.paths import CONFIG_DIR

FIXTURE = TESTS / "data" / "run_before_layout"


def _respelled(config_name, argv):
    said = []
    return current_argv(config_name, argv, said.append), said


@pytest.mark.parametrize(("config_name", "argv", "expected"), [
    ("train", ["logger=mlflow"], ["tracker=mlflow"]),
    ("train", ["logger.mlflow.check_timeout=3"], ["tracker.mlflow.check_timeout=3"]),
    ("eval", ["+logger=csv"], ["+tracker=csv"]),
    ("eval", ["++logger.wandb.project=p"], ["++tracker.wandb.project=p"]),
    ("train", ["~logger"], ["~tracker"]),
    ("train", ["-m", "logger=csv,tensorboard", "seed=1,2"], ["-m", "tracker=csv,tensorboard", "seed=1,2"]),
    ("train", ["logger=[csv,mlflow]", "--cfg", "job"], ["tracker=[csv,mlflow]", "--cfg", "job"]),
    ("map", ["rerun.spawn=false", "rerun.save=m.rrd"], ["viewer.spawn=false", "viewer.save=m.rrd"]),
    ("map_merge", ["logger=wandb"], ["tracker=wandb"]),
])  # fmt: skip
def test_an_old_spelling_is_read_as_the_new_key_with_one_warning_line(config_name, argv, expected):
    out, said = _respelled(config_name, argv)
    assert out == expected
    assert len(said) == 1, said
    old = next(o for o in RENAMED_KEYS if any(w.lstrip("+~").startswith(o) for w in argv))
    new = RENAMED_KEYS[old].new
    assert f"'{old}' is now '{new}'" in said[0] and "0.3.0" in said[0]


def test_todays_spelling_and_other_words_pass_untouched_and_silently():
    argv = ["tracker=mlflow", "experiment=smoke", "rerun.spawn=false", "loggers=1",
            "name=logger", "-m", "hydra.run.dir=logger"]  # fmt: skip
    # a train config has no rerun key (it is map.yaml's): left for the config check to name
    assert _respelled("train", argv) == (argv, [])


@pytest.mark.parametrize(("config_name", "argv"), [
    ("train", ["logger=mlflow", "tracker.mlflow.check_timeout=3"]),
    ("eval", ["tracker=csv", "~logger"]),
    ("map", ["viewer.spawn=true", "rerun.save=x.rrd"]),
])  # fmt: skip
def test_both_spellings_together_are_refused_naming_both(config_name, argv):
    with pytest.raises(ConfigError) as err:
        _respelled(config_name, argv)
    message = str(err.value)
    assert "\n" not in message
    for word in argv:
        assert word in message


def test_an_old_spelling_past_its_removal_is_refused_naming_the_release(monkeypatch):
    monkeypatch.setattr(moves, "RELEASE", "0.3.0")
    with pytest.raises(ConfigError, match=r"logger=csv: 'logger' was renamed 'tracker' in 0\.2\.0 "
                                          r"and its old spelling was removed in 0\.3\.0"):  # fmt: skip
        _respelled("train", ["logger=csv"])


def test_every_renamed_key_is_a_config_key_today_and_its_old_one_is_not():
    """The table is true of conf/: the new spelling is a top-level key (or group) of each
    config it names, the old one of none."""
    from resireg_train.jobs.overrides import top_level_keys

    for rename in RENAMED_KEYS.values():
        for name in rename.configs:
            keys = top_level_keys(name)
            assert rename.new in keys and rename.old not in keys, (name, rename)


def test_a_stored_run_is_read_in_todays_spelling_without_a_word(capsys):
    stored = {"logger": {"csv": {"filename": "metrics.csv"}}, "rerun": {"spawn": False}, "seed": 1}
    assert current_spelling(stored, "map") == {
        "tracker": {"csv": {"filename": "metrics.csv"}}, "viewer": {"spawn": False}, "seed": 1}
    assert current_spelling(stored, "train") == {
        "tracker": {"csv": {"filename": "metrics.csv"}}, "rerun": {"spawn": False}, "seed": 1}
    assert current_overrides("map", ["rerun.spawn=false", "+logger=csv", "seed=2"]) == [
        "viewer.spawn=false", "+tracker=csv", "seed=2"]  # fmt: skip
    assert capsys.readouterr() == ("", "")


def test_a_rerun_reads_a_recorded_old_spelling_as_todays(tmp_path, capsys):
    """resireg-runs rerun rebuilds a run's command from its overrides.yaml (runs/rerun/plan.py):
    an old spelling there comes back in today's, with no warning (it is not the user's
    command)."""
    from resireg_train.runs.index import read_run
    from resireg_train.runs.rerun.plan import _recorded_overrides

    folder = tmp_path / "run"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(
        yaml.safe_dump(["dataset=synthetic", "logger=csv"]))
    (folder / "results.json").write_text(json.dumps(
        {"name": "eval", "status": "completed", "final": {},
         "provenance": {"run_id": "f" * 12, "cli": "resireg-eval"}}))  # fmt: skip
    assert _recorded_overrides(read_run(folder), "eval", []) == ["dataset=synthetic",
                                                                  "tracker=csv"]  # fmt: skip
    assert "warning" not in capsys.readouterr().err


def test_a_class_of_ours_that_is_gone_and_in_no_table_is_refused_naming_it():
    # every class the moves table points at exists today (the check reads the source)
    check_stored_targets({"a": [{"_target_": t} for t in MOVED_TARGETS.values()]}, "x.yaml")
    # a library's own class is the library's: not ours to judge
    check_stored_targets({"_target_": "lightning.pytorch.loggers.Gone"}, "x.yaml")
    stored = {"model": {"_target_": "resireg_train.training.module.ResiregModule"},
              "callbacks": {"e": {"_target_": "resireg_train.evaluation.ovss.callback.Gone"}},
              "tracker": [{"_target_": "resireg_train.nowhere.Thing"}]}  # fmt: skip
    with pytest.raises(ConfigError) as err:
        check_stored_targets(stored, "run/.hydra/config.yaml", "0.1.0")
    message = str(err.value)
    assert message.startswith("run/.hydra/config.yaml: callbacks.e._target_=resireg_train."
                              "evaluation.ovss.callback.Gone; tracker[0]._target_=resireg_train."
                              "nowhere.Thing: no such class in release 0.2.0 (the run was "
                              "written by 0.1.0)"), message  # fmt: skip
    assert "ResiregModule" not in message


def _old_run(tmp_path: Path) -> Path:
    """tests/data/run_before_layout copied, its machine paths filled in (as test_train's)."""
    logs = tmp_path / "logs"
    out = logs / "smoke" / "run"
    shutil.copytree(FIXTURE, out)
    for stored in [*(out / ".hydra").glob("*.yaml"), out / "results.json"]:
        text = stored.read_text().replace("@RUN_DIR@", str(out)).replace("@LOG_DIR@", str(logs))
        stored.write_text(text.replace("@CHECKOUT@", str(CONFIG_DIR.parent)))
    return out


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def test_the_old_run_folder_spells_the_tracker_the_old_way():
    """The fixture the resume tests use was written with ``logger: csv`` (so
    test_train's resume of it covers the stored old spelling)."""
    stored = (FIXTURE / ".hydra" / "config.yaml").read_text()  # (its @LOG_DIR@: no YAML yet)
    assert "\nlogger:\n  csv:\n" in stored and "tracker" not in stored


def test_a_stored_config_naming_a_removed_class_is_refused_naming_it_and_the_release(tmp_path):
    out = _old_run(tmp_path)
    config = out / ".hydra" / "config.yaml"
    gone = "resireg_train.evaluation.ovss.callback.ReSiRegEvalGone"
    config.write_text(config.read_text().replace(
        "resireg_train.ovss.callback.ReSiRegEval", gone))  # fmt: skip
    before = _digests(out)
    overrides = yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text())
    proc = run("resireg-train", *overrides, "ckpt_path=last", f"hydra.run.dir={out}",
               check=False)  # fmt: skip
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert f"callbacks.resireg_eval._target_={gone}" in lines[0]
    assert "no such class in release 0.2.0 (the run was written by 0.1.0)" in lines[0]
    assert _digests(out) == before  # nothing of the run changed


@pytest.mark.slow
def test_the_real_train_command_takes_the_old_spellings_and_records_the_new(tmp_path):
    """A multirun over ``logger=csv,tensorboard`` (and ``~logger`` alone) through the real
    resireg-train: one warning line naming ``tracker``; each job's recorded config and
    overrides hold ``tracker``, never ``logger``. The jobs stop at the config check (an added
    key nothing reads), after Hydra wrote their records, so no model loads."""
    sweep = tmp_path / "sweep"
    proc = run("resireg-train", "-m", "experiment=smoke", "logger=csv,tensorboard",
               "+batchsize=4", f"hydra.sweep.dir={sweep}", check=False)  # fmt: skip
    warnings = [line for line in proc.stderr.splitlines() if "warning:" in line]
    assert warnings == ["resireg-train: warning: 'logger' is now 'tracker' (renamed in 0.2.0; "
                        "the old spelling goes in 0.3.0): read logger=csv,tensorboard -> "
                        "tracker=csv,tensorboard"], proc.stderr[-3000:]  # fmt: skip
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 2, jobs
    for job, chosen in zip(jobs, ("csv", "tensorboard"), strict=True):
        config = yaml.safe_load((job / ".hydra" / "config.yaml").read_text())
        assert "logger" not in config and list(config["tracker"]) == [chosen], config
        recorded = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
        assert f"tracker={chosen}" in recorded and not any("logger" in o for o in recorded)

    out = tmp_path / "file"
    proc = run("resireg-train", "experiment=smoke", "logger=csv", "logger.csv.filename=m.csv",
               "+batchsize=4", f"hydra.run.dir={out}", check=False)  # fmt: skip
    assert proc.stderr.count("'logger' is now 'tracker'") == 1, proc.stderr[-3000:]
    config = yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    assert config["tracker"] == {"csv": {"filename": "m.csv"}} and "logger" not in config

    out = tmp_path / "none"
    proc = run("resireg-train", "experiment=smoke", "~logger", "+batchsize=4",
               f"hydra.run.dir={out}", check=False)  # fmt: skip
    assert "'logger' is now 'tracker'" in proc.stderr
    config = yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    assert "tracker" not in config and "logger" not in config


def test_both_spellings_on_the_real_command_exit_1_in_one_line_naming_both(tmp_path):
    out = tmp_path / "run"
    proc = run("resireg-train", "experiment=smoke", "logger=mlflow", "tracker.mlflow.check_timeout=3",
               f"hydra.run.dir={out}", check=False)  # fmt: skip
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "resireg-train: error: logger=mlflow tracker.mlflow.check_timeout=3: 'logger' and "
        "'tracker' name one setting ('logger' is the old spelling of 'tracker'): give it once, "
        "as 'tracker'"]  # fmt: skip
    assert not out.exists()


def test_the_real_map_command_takes_rerun_as_viewer(tmp_path):
    """resireg-map rerun.spawn=false: one warning naming ``viewer``; the run's recorded
    config holds ``viewer`` with the value (the job then stops: no source given)."""
    out = tmp_path / "map"
    proc = run("resireg-map", "rerun.spawn=false", "rerun.map_every=2", f"hydra.run.dir={out}",
               check=False)  # fmt: skip
    warnings = [line for line in proc.stderr.splitlines() if "warning:" in line]
    assert len(warnings) == 1 and "'rerun' is now 'viewer'" in warnings[0], proc.stderr[-3000:]
    config = yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    assert "rerun" not in config
    assert config["viewer"]["spawn"] is False and config["viewer"]["map_every"] == 2
    assert yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text()) == [
        "viewer.spawn=false", "viewer.map_every=2"]  # fmt: skip


@pytest.mark.slow
def test_a_training_run_in_the_old_spelling_completes_and_resumes_silently(tmp_path):
    """A whole smoke training with ``logger=tensorboard``: completed, its TensorBoard logs
    written, its record holding ``tracker``; resumed with its own recorded overrides (today's
    spelling) it restores from its checkpoint without a warning."""
    out = tmp_path / "run"
    common = ["experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2", "export=false"]
    proc = run("resireg-train", *common, "logger=tensorboard", f"hydra.run.dir={out}")
    assert proc.stderr.count("'logger' is now 'tracker'") == 1
    assert json.loads((out / "results.json").read_text())["status"] == "completed"
    assert any((out / "tensorboard").rglob("events.out.tfevents.*"))
    assert "tracker" in yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    recorded = yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text())
    proc = run("resireg-train", *recorded, "ckpt_path=last", f"hydra.run.dir={out}")
    assert "Restored all states from the checkpoint" in proc.stdout + proc.stderr
    assert "warning:" not in proc.stderr


def test_a_search_record_in_the_old_spelling_starts_workers_in_todays(tmp_path, capsys):
    """A search's record (``search.json``, written before the rename) gives its workers the
    overrides in today's spelling, silently: a worker's command is not the user's."""
    from resireg_train.search.workers import RECORD_FORMAT, SEARCH_FILE, read_record, worker_command

    (tmp_path / SEARCH_FILE).write_text(json.dumps(
        {"format": RECORD_FORMAT, "job": "train", "storage": None, "study_name": "s",
         "overrides": ["experiment=smoke", "logger=csv", "hparams_search=resireg_optuna"]}))  # fmt: skip
    assert read_record(tmp_path).overrides == ("experiment=smoke", "tracker=csv",
                                               "hparams_search=resireg_optuna")  # fmt: skip
    assert "tracker=csv" in worker_command(tmp_path) and "logger=csv" not in worker_command(tmp_path)
    assert "warning" not in capsys.readouterr().err


def test_a_rerun_of_a_run_naming_a_gone_class_is_refused_naming_it(tmp_path, capsys):
    """resireg-runs rerun of a run whose stored config names a class of ours that is gone and
    in no moves table: one line naming the key, the class and the releases; nothing started."""
    from resireg_train.cli.runs import main

    folder = tmp_path / "run"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(["dataset=synthetic"]))
    (folder / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"seed": 0, "prior": {"_target_": "resireg_train.gone.Prior"}}))
    (folder / "results.json").write_text(json.dumps(
        {"name": "eval", "status": "completed", "final": {},
         "provenance": {"run_id": "f" * 12, "cli": "resireg-eval", "code": {"version": "0.1.0"}}}))  # fmt: skip
    with pytest.raises(SystemExit) as exit_:
        main(["rerun", str(folder), "--out", str(tmp_path / "again")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert ("prior._target_=resireg_train.gone.Prior: no such class in release 0.2.0 (the run "
            "was written by 0.1.0)") in err
    assert not (tmp_path / "again").exists()


def test_the_warning_masks_a_password_it_repeats(tmp_path):
    """The warning repeats the overrides it read: a tracking URI's password is masked there
    as everywhere the run prints (resireg.secrets)."""
    proc = run("resireg-train", "experiment=smoke", "logger=mlflow",
               "logger.mlflow.tracking_uri=http://ann:hunter2@127.0.0.1:9", "--cfg", "job")  # fmt: skip
    assert "hunter2" not in proc.stdout + proc.stderr
    (warning,) = [line for line in proc.stderr.splitlines() if "warning:" in line]
    assert "tracker.mlflow.tracking_uri=http://ann:***@127.0.0.1:9" in warning, warning
