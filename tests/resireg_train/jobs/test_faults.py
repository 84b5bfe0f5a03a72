"""Bad inputs and faults as users meet them: poisoned evaluation data, Ctrl-C, a full disk,
a corrupt checkpoint, a resume with another schedule, batch-job logs."""

import errno
import json
import os
import re
import resource
import shlex
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from helpers.ade20k import poisoned_ade_folder
from helpers.paths import TESTS
from helpers.run import evaluate, run, run_side_by_side
from resireg_train.training.checkpoints import CheckpointError, resolve_checkpoint

SMOKE = ("experiment=smoke", "data.steps_per_epoch=4", "callbacks.resireg_eval.num_workers=0")


def _train(out, *overrides, check=True, **kwargs):
    return run("resireg-train", *SMOKE, f"hydra.run.dir={out}", *overrides, check=check, **kwargs)


def _env_with_tests():
    """This environment, with tests/ importable (the fault callbacks of helpers/faults.py)."""
    return {**os.environ,
            "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}  # fmt: skip


def _results(out):
    """The run's results.json as a strict JSON parser reads it (a bare NaN is an error)."""

    def refuse(name):
        raise ValueError(f"results.json is not strict JSON: {name}")

    return json.loads((Path(out) / "results.json").read_text(), parse_constant=refuse)


# --------------------------------------------------------------------- bad labels (item 3)
@pytest.mark.slow
def test_poisoned_ade20k_folder_trains_and_evaluates_naming_the_bad_samples(tmp_path):
    """Out-of-range id, RGB label, wrong-size label and truncated image: training goes on,
    every epoch counts 4 skips and results.json names each file with its reason; resireg-eval
    on the export (with no ReSiReg arguments: the export records them) reproduces the
    training score, skips the same 4, and scores exactly what a folder holding only the good
    images scores (both evaluations run resireg-eval's task in this process). Its batch-size
    histogram counts the batches scored."""
    bad = poisoned_ade_folder(tmp_path / "ade")
    clean = tmp_path / "clean"
    for sub in ("images", "annotations"):
        (clean / sub / "validation").mkdir(parents=True)
        for f in (tmp_path / "ade" / sub / "validation").iterdir():
            if f"{f.stem}.jpg" not in bad:
                (clean / sub / "validation" / f.name).write_bytes(f.read_bytes())
    ade = "callbacks.resireg_eval.datasets.ade20k"
    out = tmp_path / "run"
    # open_clip's 7 simple templates throughout (ADE20K's 150 classes x the protocol's 80
    # templates, prompted three times, were a third of this test's time)
    proc = _train(out, "trainer.max_epochs=2", "val_data=ade20k", f"{ade}.path={tmp_path / 'ade'}",
                  f"{ade}.short_side=32", f"{ade}.templates=simple_imagenet",
                  "callbacks.resireg_eval.batch_size=2",
                  "callbacks.resireg_eval.full.n_prototypes=4")  # fmt: skip
    results = _results(out)
    assert results["status"] == "completed"
    assert [h["val/ovss/ade20k/skipped"] for h in results["history"]] == [4, 4]
    named = {Path(s["file"]).name: s["reason"] for s in results["skipped_samples"]["ade20k"]}
    assert set(named) == set(bad)
    for name, pattern in bad.items():
        assert re.search(pattern, named[name]), (name, named[name])
    log = (out / "train.log").read_text()
    assert log.count("ade20k: skipped 4 of 9 images") == 1  # named once, not every epoch
    assert all(name in log for name in bad)
    assert "skipped 4 of 9" in proc.stdout + proc.stderr

    scores = {}
    for name, path in (("poisoned", tmp_path / "ade"), ("clean", clean)):
        # resireg-eval's task in this process (its command line: these overrides alone)
        evaluate(f"model_path={out / 'export'}", "dataset=ade20k", f"dataset.path={path}",
                 "dataset.short_side=32", "dataset.templates=simple_imagenet", "num_workers=0",
                 f"paths.output_dir={tmp_path / name}")  # fmt: skip
        scores[name] = _results(tmp_path / name)
    poisoned = scores["poisoned"]
    assert poisoned["params"]["batch_size"] == 2 and poisoned["params"]["full"]["n_prototypes"] == 4
    assert poisoned["images"] == 5 and poisoned["skipped"] == 4
    assert {Path(s["file"]).name for s in poisoned["skipped_samples"]} == set(bad)
    # 9 images in batches of 2 of one size: planned [2, 2, 2, 2, 1]; scored after the skips:
    # [0, 1], [2, 3], [14] (10 + 11 and 12 + 13 lost both their images).
    assert poisoned["batch_sizes"] == {"1": 1, "2": 2}
    assert poisoned["final"] == scores["clean"]["final"]
    final = results["history"][-1]
    for key, value in poisoned["final"].items():
        assert value == pytest.approx(final[key], abs=1e-6), key


# ------------------------------------------------------------------------- Ctrl-C (item 4)
def _snapshot(folder):
    """Every file under ``folder`` and its bytes."""
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_ctrl_c_is_recorded_as_interrupted_and_the_printed_command_resumes_it(tmp_path):
    """Ctrl-C records the command that resumes the run (issue 22, case 6): the run's own
    overrides. A resume that composes another config (the bare `ckpt_path=last hydra.run.dir=`,
    or a longer schedule) and a new run pointed at the folder are refused before anything is
    written, naming the differing keys; the printed command, run verbatim, completes the run."""
    out = tmp_path / "run"
    env = _env_with_tests()
    stop = ["+callbacks.stop._target_=helpers.faults.SigintAt", "+callbacks.stop.epoch=1"]
    proc = _train(out, "trainer.max_epochs=3", *stop, check=False, env=env)
    assert proc.returncode == 130, proc.stderr[-2000:]
    results = _results(out)
    assert results["status"] == "interrupted"
    hint = "KeyboardInterrupt: interrupted by the user (Ctrl-C); resume with "
    assert results["error"].startswith(hint)
    command = shlex.split(results["error"][len(hint) :])
    assert command == ["resireg-train", *SMOKE, "trainer.max_epochs=3", *stop, "ckpt_path=last",
                       f"hydra.run.dir={out}"]  # fmt: skip
    assert [h["epoch"] for h in results["history"]] == [0]
    before = _snapshot(out)

    commands = {
        "bare": ("ckpt_path=last", f"hydra.run.dir={out}"),
        # a longer schedule would jump the learning rate
        "longer": (*SMOKE, f"hydra.run.dir={out}", "trainer.max_epochs=5", *stop, "ckpt_path=last"),
        "fresh": (*SMOKE, f"hydra.run.dir={out}", "trainer.max_epochs=3"),
    }
    # Independent refusals (none may write): started side by side; each is checked below.
    procs = run_side_by_side(*(("resireg-train", *args) for args in commands.values()),
                             check=False, env=env, threads=None)  # fmt: skip
    refused = dict(zip(commands, procs, strict=True))
    for name, proc in refused.items():
        assert proc.returncode == 1, name
        assert _snapshot(out) == before, name  # nothing under the run was rewritten
        (line,) = [x for x in proc.stderr.splitlines() if x.startswith("resireg-train: refused")]
        if name == "fresh":
            assert (
                f"hydra.run.dir={out} already holds a run ('smoke', status 'interrupted')" in line
            )
            continue
        assert f"this command's config differs from the run's ({out}/.hydra/config.yaml)" in line
        assert f"Resume with the run's own overrides: {shlex.join(command)};" in line
        assert f"model.init_from={out}/checkpoints/last.ckpt" in line
        if name == "longer":
            assert "in 1 key(s): trainer.max_epochs=5 (the run: 3). " in line, line
        else:  # the default config: the smoke experiment's values are named
            assert "name='train' (the run: 'smoke')" in line and "and " in line, line

    run(*command, env=env)  # the printed command, verbatim (asserts it succeeds)
    results = _results(out)
    assert results["status"] == "completed" and results["error"] is None
    assert [h["epoch"] for h in results["history"]] == [0, 1, 2]


# ---------------------------------------------------------------------- full disk (item 4)
#: The environment of a process under a file-size limit: git finds no checkout, so the run
#: records no code.diff of this checkout's uncommitted change (its size is not this test's).
NO_CHECKOUT = {**os.environ, "GIT_DIR": os.devnull}


def _file_size_limit(limit):
    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_write_failing_midway_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    """A real failed write: a process that may not write files over 4 KB (RLIMIT_FSIZE, as
    a full disk or a quota would refuse) rewrites results.json with 10 KB."""
    target = tmp_path / "results.json"
    target.write_text('{"status": "running"}')
    code = (
        "import sys; from resireg.integrity import atomic_write\n"
        "try:\n    atomic_write(sys.argv[1], 'x' * 10_000, what='run record')\n"
        "except OSError as err:\n    print(type(err).__name__, err.errno, err)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(target)], capture_output=True, text=True,
        preexec_fn=_file_size_limit(4096), timeout=60,
    )  # fmt: skip
    assert proc.stdout.strip() == (
        f"WriteError {errno.EFBIG} could not write the run record {target}: File too large"
    ), proc.stderr
    assert target.read_text() == '{"status": "running"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


@pytest.mark.slow
def test_a_checkpoint_that_cannot_be_written_fails_in_one_line_and_leaves_nothing(tmp_path):
    """A real write failure: the process may not write files over 512 KB (RLIMIT_FSIZE, as
    a full disk or a quota would refuse), and a smoke checkpoint is ~1.4 MB."""
    out = tmp_path / "run"
    proc = run("resireg-train", *SMOKE, "trainer.max_epochs=1", f"hydra.run.dir={out}",
               check=False, preexec=_file_size_limit(512 * 1024), env=NO_CHECKOUT)  # fmt: skip
    assert proc.returncode != 0
    target = out / "checkpoints" / "epoch000.ckpt"
    expected = f"could not write the checkpoint {target}: File too large"
    results = _results(out)
    assert (
        results["status"] == "failed"
        and results["error"] == f"resireg.errors.WriteError: {expected}"
    )
    said = [line for line in proc.stderr.splitlines() if line.strip()]
    assert said[-2] == f"resireg.errors.WriteError: {expected}"  # then Hydra's hint
    assert list((out / "checkpoints").iterdir()) == []  # no truncated file, no temporary


# ------------------------------------------------------------- corrupt checkpoint (item 4)
@pytest.fixture(scope="module")
def two_epochs(tmp_path_factory):
    """A 2-epoch smoke run keeping every epoch's checkpoint, its stdout piped (as in a batch
    job); returns (folder, completed process)."""
    out = tmp_path_factory.mktemp("two_epochs") / "run"
    proc = _train(out, "trainer.max_epochs=2", "callbacks.model_checkpoint.save_top_k=-1")
    return out, proc


def _corrupt(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])


@pytest.mark.slow
def test_a_corrupt_last_checkpoint_resumes_from_the_newest_readable_one(two_epochs, tmp_path):
    source, _ = two_epochs
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    for name in ("epoch000.ckpt", "epoch001.ckpt", "last.ckpt"):
        (out / "checkpoints" / name).write_bytes((source / "checkpoints" / name).read_bytes())
    os.utime(out / "checkpoints" / "epoch000.ckpt", (1, 1))  # the oldest
    _corrupt(out / "checkpoints" / "last.ckpt")
    _corrupt(out / "checkpoints" / "epoch001.ckpt")
    proc = _train(out, "trainer.max_epochs=2", "ckpt_path=last")
    said = proc.stdout + proc.stderr
    assert re.search(r"last\.ckpt \(\w+Error.*epoch001\.ckpt \(\w+Error.*unreadable; resuming "
                     r"from \S*epoch000\.ckpt \(global step 4\) instead", said), said[-3000:]  # fmt: skip
    results = _results(out)
    assert results["status"] == "completed" and [h["epoch"] for h in results["history"]] == [0, 1]
    assert results["global_step"] == 8


def test_no_readable_checkpoint_fails_naming_the_files_and_the_options(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    torch.save({"global_step": 3}, folder / "epoch000.ckpt")
    (folder / "last.ckpt").write_bytes(b"PK\x03\x04 truncated")
    path, content = resolve_checkpoint("last", tmp_path)
    assert Path(path).name == "epoch000.ckpt" and content["global_step"] == 3
    _corrupt(folder / "epoch000.ckpt")
    with pytest.raises(CheckpointError) as err:
        resolve_checkpoint("last", tmp_path)
    message = str(err.value)
    assert "last.ckpt (" in message and "epoch000.ckpt (" in message
    assert "Remove the unreadable files" in message and "set ckpt_path" in message
    with pytest.raises(CheckpointError, match=r"ckpt_path='\S+last\.ckpt' cannot be read"):
        resolve_checkpoint(str(folder / "last.ckpt"), tmp_path)
    assert resolve_checkpoint("last", tmp_path / "fresh") is None  # nothing yet: from scratch


# ------------------------------------------------------------------ batch-job logs (item 5)
@pytest.mark.slow
def test_train_log_and_piped_stdout_have_one_line_per_epoch_and_no_noise(two_epochs):
    """One line per epoch in train.log and the piped stdout, numbered as the checkpoint files
    are (from 0, as Lightning's bar; issue 22, case 13), no progress bar drawn into the pipe,
    none of the silenced library messages."""
    out, proc = two_epochs
    line = re.compile(r"epoch (\d)/1 \| train/logit_scale=\S+ train/loss=\S+ .*train/lr=\S+ .*"
                      r"val/ovss/synthetic/miou_full=\S+ .*data/skipped_invalid=0 "
                      r"data/skipped_small=0 \| 4 steps \| [\d.]+ s$")  # fmt: skip
    logged = [
        m.group(1) for m in map(line.search, (out / "train.log").read_text().splitlines()) if m
    ]
    assert logged == ["0", "1"]
    printed = [m.group(1) for m in map(line.search, proc.stdout.splitlines()) if m]
    assert printed == ["0", "1"]
    files = sorted(p.name for p in (out / "checkpoints").glob("epoch*.ckpt"))
    assert files == [f"epoch00{n}.ckpt" for n in printed]
    assert [h["epoch"] for h in _results(out)["history"]] == [int(n) for n in printed]
    said = proc.stdout + proc.stderr
    for noise in ("in eval mode at the start of training", "litlogger", "LeafSpec",
                  "has `__len__` defined", "it/s", "Epoch 1/1"):  # fmt: skip
        assert noise not in said, noise  # (the last two: a progress bar)


def test_skipped_caption_examples_are_reported_once_per_epoch_with_the_epoch_totals(caplog):
    """The epoch's data/skipped_* sums (over steps, workers and ranks) in one warning."""
    from resireg_train.training.console import EpochLog

    trainer = SimpleNamespace(
        is_global_zero=True, callbacks=[], current_epoch=1, max_epochs=3, global_step=16,
        callback_metrics={"train/loss_epoch": torch.tensor(2.5), "train/loss_step": torch.tensor(9.0),
                          "data/skipped_invalid": torch.tensor(3.0),
                          "data/skipped_small": torch.tensor(2.0)},
    )  # fmt: skip
    callback = EpochLog()
    callback._first_step = 8
    with caplog.at_level("INFO"):
        callback.on_train_epoch_end(trainer, None)
    (line,) = [r.getMessage() for r in caplog.records if r.levelname == "INFO"]
    assert re.fullmatch(r"epoch 1/2 \| train/loss=2\.5 data/skipped_invalid=3 "
                        r"data/skipped_small=2 \| 8 steps \| [\d.]+ s", line)  # fmt: skip
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert (
        warning == "epoch 1: skipped 5 caption examples (invalid 3, small 2; all workers and ranks)"
    )


# ------------------------------------------------------------- smaller defects (item 6)
def test_text_weights_null_and_a_missing_gpu_name_the_key_and_the_fix(monkeypatch):
    from hydra import compose, initialize_config_dir

    from resireg.errors import ConfigError
    from resireg_train.checks.train import validate
    from resireg_train.config.machine import check_devices
    from resireg_train.config.paths import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        stage1 = compose("train", overrides=["experiment=vlm25m_stage1", "model.text.weights=null"])
        smoke = compose("train", overrides=["experiment=smoke"])
    with pytest.raises(ConfigError, match=r"model\.text\.weights=None: expected an open_clip "
                       r"pretrained tag of model\.text\.model_name='ViT-B-16-SigLIP2'"):  # fmt: skip
        validate(stage1)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match=r"trainer\.accelerator='gpu': this machine has no CUDA "
                       r"GPU .*use trainer=cpu"):  # fmt: skip
        check_devices(stage1)
    check_devices(smoke)  # trainer=cpu
    with pytest.raises(
        ConfigError, match=r"device='cuda:1': this machine has no CUDA GPU.*use cpu"
    ):
        check_devices({"device": "cuda:1"})
    check_devices({"device": "auto"})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ConfigError, match=r"device='cuda:1': this machine has 1 CUDA device"):
        check_devices({"device": "cuda:1"})
    check_devices(stage1)


def test_export_settings_fill_only_the_values_left_at_their_default(tmp_path):
    from hydra import compose, initialize_config_dir

    from resireg_train.config.paths import CONFIG_DIR
    from resireg_train.evaluation.ovss.settings import save_settings
    from resireg_train.jobs.eval import with_export_settings

    save_settings(tmp_path, {"variants": ["bb", "full"], "batch_size": 2, "precision": "32",
                             "full": {"n_prototypes": 12, "alpha": 5.0}, "lite": {}})  # fmt: skip
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        plain = compose("eval", overrides=[f"model_path={tmp_path}"])
        chosen = compose("eval", overrides=[f"model_path={tmp_path}", "batch_size=4"])
        sweep = compose("eval", overrides=[f"model_path={tmp_path}", "sweep=prototype_batch"])
        off = compose("eval", overrides=[f"model_path={tmp_path}", "export_settings=false"])
    cfg, taken = with_export_settings(plain)
    assert sorted(taken) == ["batch_size", "full.n_prototypes", "variants"]  # alpha: same value
    assert (cfg.batch_size, cfg.full.n_prototypes, list(cfg.variants)) == (2, 12, ["bb", "full"])
    cfg, taken = with_export_settings(chosen)
    assert cfg.batch_size == 4 and "batch_size" not in taken and cfg.full.n_prototypes == 12
    cfg, taken = with_export_settings(sweep)
    assert cfg.variants[0] == "full@n_prototypes:24" and "variants" not in taken  # the sweep file
    assert with_export_settings(off) == (off, [])


# ------------------------------------------------- nothing scored (issue 22, case 3)
@pytest.mark.slow
def test_a_dataset_whose_every_image_is_bad_fails_with_the_skip_counts(tmp_path, tiny_export):
    """No image scored is no score: the run fails (non-zero exit through Hydra), its error
    gives the counts and the first file, and results.json still names every skipped one."""
    from hydra import compose, initialize_config_dir

    from resireg_train.cli.eval import evaluate
    from resireg_train.config.paths import CONFIG_DIR
    from resireg_train.evaluation.base import NothingScoredError

    bad = poisoned_ade_folder(tmp_path / "ade")
    for sub in ("images", "annotations"):
        for f in (tmp_path / "ade" / sub / "validation").iterdir():
            if f"{f.stem}.jpg" not in bad:
                f.unlink()
    out = tmp_path / "run"
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=[
            f"model_path={tiny_export}", "dataset=ade20k", f"dataset.path={tmp_path / 'ade'}",
            "dataset.short_side=32", "num_workers=0", "variants=[bb]", f"paths.output_dir={out}",
        ])  # fmt: skip
    with pytest.raises(NothingScoredError) as err:
        evaluate(cfg)
    first = sorted(bad)[0]
    assert re.match(
        rf"dataset=ade20k: no image was scored: 4 of 4 images skipped \(unreadable or invalid\); "
        rf"the first: \S+/{first}: .*{bad[first]}",
        str(err.value),
    ), str(err.value)
    results = _results(out)
    assert results["status"] == "failed" and results["error"].endswith(str(err.value))
    assert results["images"] == 0 and results["skipped"] == 4
    # Its scores over nothing are NaN: null in the file (strict JSON, case 4), and listed.
    assert set(results["final"].values()) == {None}
    nan = results["non_finite"]["NaN"]
    assert {"/final/" + k.replace("/", "~1") for k in results["final"]} <= set(nan)
    assert {Path(s["file"]).name for s in results["skipped_samples"]} == set(bad)


# ------------------------------------------- errors in the log files (issue 22, case 5)
@pytest.mark.slow
def test_a_failed_run_writes_its_error_to_its_log_and_a_sweep_lists_every_failed_job(tmp_path):
    """Config errors of a 3-job training multirun: each job's train.log holds its error, the
    console shows no traceback for them (case 13) and ends with one line per failed job. A
    crash (not a config error) puts its traceback into train.log as well."""
    proc = run("resireg-train", "-m", *SMOKE, "model.optimizer.lr=-1,-2,-3",
               f"paths.log_dir={tmp_path}", check=False)  # fmt: skip
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    (sweep,) = (tmp_path / "smoke" / "multirun").iterdir()
    jobs = sorted(
        (p for p in sweep.iterdir() if p.is_dir()), key=lambda p: int(p.name.split("_")[0])
    )
    tail = proc.stderr.strip().splitlines()[-4:]
    assert tail[0] == (f"resireg-train: 3 of 3 jobs failed (sweep {sweep}; resireg-report {sweep} "
                       "lists every job):")  # fmt: skip
    for n, (line, job) in enumerate(zip(tail[1:], jobs, strict=True)):
        lr = -(n + 1)
        assert line == (
            f"  job {n} ({job.name}): resireg.errors.ConfigError: invalid config: "
            f"model.optimizer.lr={lr}: expected a number > 0; model.scheduler.min_lr=1e-05: "
            f"expected <= model.optimizer.lr={lr}"
        )
        log = (job / "train.log").read_text()
        assert f"run failed: resireg.errors.ConfigError: invalid config:\n  " \
               f"model.optimizer.lr={lr}: expected a number > 0" in log, log  # fmt: skip
        assert _results(job)["status"] == "failed"

    out = tmp_path / "crash"
    proc = _train(out, "trainer.max_epochs=1", "+callbacks.crash._target_=helpers.faults.RaiseAt",
                  check=False, env=_env_with_tests())  # fmt: skip
    assert proc.returncode == 1 and "RuntimeError: injected crash" in proc.stderr
    log = (out / "train.log").read_text()
    assert re.search(r"\[ERROR\] - run failed: RuntimeError: injected crash\nTraceback \(most "
                     r"recent call last\):\n(.*\n)*.*helpers/faults\.py.*on_train_start", log), log  # fmt: skip


# --------------------------------- a final status that cannot be written (issue 22, case 11)
_RUN_TASK = (
    "import sys\n"
    "from omegaconf import OmegaConf\n"
    "from resireg_train.cli.job import run_task\n"
    "def body(cfg, record):\n"
    "    if sys.argv[2] == 'crash':\n"
    "        raise RuntimeError('x' * 8000)  # a failure too long to record under the limit\n"
    "    return record.update(status='completed', final={'m': 0.5}, pad='x' * 8000)\n"
    "run_task(OmegaConf.create({'name': 'n', 'paths': {'output_dir': sys.argv[1]}}), body)\n"
)


@pytest.mark.parametrize("how", ["record", "crash"])
def test_a_final_status_reaches_the_record_or_stderr_says_it_could_not(tmp_path, how):
    """A process that may not write files over 4 KB (RLIMIT_FSIZE, as a nearly full disk):
    its small `running` record is written, the large final one is not. `record`: the run
    fails on that write and its `failed` status (short) reaches results.json. `crash`: the
    `failed` record, holding a long error, cannot be written either: stderr says so, naming
    the status the record still reads. Both exit non-zero."""
    proc = subprocess.run(
        [sys.executable, "-c", _RUN_TASK, str(tmp_path), how], capture_output=True, text=True,
        preexec_fn=_file_size_limit(4096), timeout=120, env=NO_CHECKOUT,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-2000:]
    results = _results(tmp_path)
    if how == "record":
        assert results["status"] == "failed"
        assert results["error"] == (f"resireg.errors.WriteError: could not write the run "
                                    f"record {tmp_path}/results.json: File too large")  # fmt: skip
    else:
        assert results["status"] == "running"
        said = proc.stderr.splitlines()[0]
        assert said.startswith(
            f"error: could not record status 'failed' in {tmp_path}/results.json (could not "
            f"write the run record {tmp_path}/results.json: File too large); it still reads "
            "status 'running' although the run ended 'failed': RuntimeError: xxx"
        ), said[:400]


def test_eval_into_a_used_folder_starts_a_fresh_record(tmp_path, tiny_export):
    """A second resireg-eval into the same hydra.run.dir writes only its own fields: the
    first run's elbo_prototypes (written only when an elbo configuration runs) does not
    survive into the second's results.json, and the first record is kept whole beside it.
    Both run resireg-eval's task in this process (the record is the task's, not Hydra's)."""
    common = (f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
              "num_workers=0", f"paths.output_dir={tmp_path}")  # fmt: skip
    evaluate(*common, "variants=[bb,full@n_prototypes:elbo]", "full.elbo_candidates=[2,4]")
    first = json.loads((tmp_path / "results.json").read_text())
    assert "elbo_prototypes" in first
    evaluate(*common, "variants=[bb]")
    second = json.loads((tmp_path / "results.json").read_text())
    assert second["status"] == "completed" and "elbo_prototypes" not in second
    assert set(second["final"]) == {k for k in first["final"] if k.endswith("_bb")}
    assert json.loads((tmp_path / "results.previous-1.json").read_text()) == first
