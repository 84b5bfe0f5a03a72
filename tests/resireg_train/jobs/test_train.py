"""Hydra configs and the `resireg-train` entry point: recipe, smoke run, resume, bad config."""

import csv
import json
import math
import re
import shutil

import lightning as L
import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from helpers.paths import TESTS
from helpers.run import evaluate_export, run, run_side_by_side
from resireg.errors import ConfigError
from resireg.models import ResiregVLM
from resireg_train.checks.train import validate
from resireg_train.cli.job import CONFIG_DIR, optimized_value
from resireg_train.cli.train import train
from resireg_train.jobs.train import build
from resireg_train.training.module import ResiregModule


def _compose(*overrides):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=list(overrides))


# docs/method.md#training-recipe, key by key.
RECIPE = {
    "trainer.max_epochs": (100, 350),
    "data.batch_size": (48, 48),
    "data.steps_per_epoch": (1000, 1000),
    "data.crop_size": (512, 512),
    "model.optimizer._target_": ("torch.optim.AdamW", "torch.optim.AdamW"),
    "model.optimizer.lr": (6e-4, 4e-4),
    "model.scheduler.min_lr": (1e-6, 5e-6),
    "model.optimizer.weight_decay": (0.05, 0.05),
    "model.loss.contrastive.scale": (1.0, 1.0),
    "model.loss.contrastive.warmup_epochs": (4, 4),
    "model.loss.distill.scale": (0.1, 0.0),
    "model.logit_scale.init": (1 / 0.07, 1 / 0.07),
    "model.logit_scale.max": (100.0, 100.0),
    "trainer.precision": ("bf16-mixed", "bf16-mixed"),
}


@pytest.mark.parametrize("stage", [1, 2])
def test_experiment_configs_carry_the_recipe_table(stage):
    cfg = _compose(f"experiment=vlm25m_stage{stage}")
    for key, values in RECIPE.items():
        got = OmegaConf.select(cfg, key)
        assert got == pytest.approx(values[stage - 1]), key
    assert cfg.model.backbone.model_name == "eupe_vit_s16" and cfg.model.backbone.weights == "hub"
    assert cfg.model.text.model_name == "ViT-B-16-SigLIP2" and cfg.model.text.weights == "webli"
    assert (cfg.model.head.depth, cfg.model.head.num_heads, cfg.model.head.out_dim) == (2, 8, 512)
    assert cfg.model.head.drop_path == 0.3 and cfg.model.head.mlp_ratio == 4.0
    if stage == 1:
        assert cfg.model.loss.distill.warmup_epochs == 8
        assert cfg.model.teacher.kind == "radseg"
        assert cfg.model.teacher.model_version == "c-radio_v3-b"
        assert cfg.model.teacher.lang_model == "siglip2"
        assert "init_from" not in cfg.model
        validate(cfg)
        # a source's weight in the mix has no default: conf/data/ sets it
        del cfg.data.sources.pexels.probability
        with pytest.raises(ConfigError, match=r"no data\.sources\.pexels\.probability"):
            validate(cfg)
    else:
        assert cfg.model.teacher is None
        assert OmegaConf.is_missing(cfg.model, "init_from")  # stage 2 must name stage 1
        with pytest.raises(ConfigError, match=r"model\.init_from=\?\?\?"):
            validate(cfg)
        validate(_compose("experiment=vlm25m_stage2", "model.init_from=stage1/last.ckpt"))


def test_resireg_parameters_have_one_source_for_eval_and_the_callback():
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        evaluation = compose("eval", overrides=["model_path=x"])
    callback = _compose().callbacks.resireg_eval
    group = OmegaConf.load(CONFIG_DIR / "resireg" / "default.yaml")
    for key in ("variants", "calib", "lite", "full"):
        assert evaluation[key] == callback[key] == group[key], key
    assert group.full.n_components is None  # tied to n_prototypes in both


def _leaves(node, prefix=""):
    if isinstance(node, dict):
        return {
            k: v for key, sub in node.items() for k, v in _leaves(sub, f"{prefix}{key}.").items()
        }
    return {prefix[:-1]: node}


@pytest.mark.parametrize("name", ["smoke", "vlm25m_stage1", "vlm25m_stage2"])
def test_experiment_files_state_only_what_differs_from_their_base_groups(name):
    """Every value an experiment file sets differs from what its base groups give."""
    raw = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "experiment" / f"{name}.yaml"))
    groups = [
        f"{k.removeprefix('override /')}={v}"
        for entry in raw.pop("defaults", [])
        for k, v in entry.items()
    ]
    base = OmegaConf.to_container(_compose(*groups))
    composed = OmegaConf.to_container(_compose(f"experiment={name}"))
    base_leaves, leaves = _leaves(base), _leaves(composed)
    for key in _leaves(raw):
        if key == "name":
            continue
        assert leaves.get(key, "<absent>") != base_leaves.get(key, "<absent>"), key


def test_callback_resireg_values_are_checked_before_training(tmp_path):
    with pytest.raises(ConfigError) as err:
        validate(_compose("experiment=smoke", "callbacks.resireg_eval.full.alpha=0",
                          "callbacks.resireg_eval.variants=[bb,mid]"))  # fmt: skip
    assert "callbacks.resireg_eval.full.alpha=0: expected a number > 0" in str(err.value)
    assert "callbacks.resireg_eval.variants=['bb', 'mid']" in str(err.value)
    # More prototypes than a validation batch has points: found at setup, before epoch 0.
    cfg = _compose("experiment=smoke", f"paths.output_dir={tmp_path}", "~callbacks.progress_bar",
                   "callbacks.resireg_eval.full.n_prototypes=100000")  # fmt: skip
    with pytest.raises(
        ValueError, match=r"callbacks\.resireg_eval\.full: n_prototypes=100000 exceeds"
    ):
        train(cfg)
    assert not (tmp_path / "checkpoints").exists()
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["status"] == "failed" and "epoch" not in results


def test_bad_config_values_fail_fast_naming_key_and_value(tmp_path):
    cfg = _compose(
        "experiment=smoke",
        f"paths.output_dir={tmp_path}",
        "model.optimizer.lr=-0.1",
        "data.batch_size=abc",
        "model.head.drop_path=1.5",
    )
    with pytest.raises(ConfigError) as err:
        train(cfg)
    message = str(err.value)
    assert "model.optimizer.lr=-0.1: expected a number > 0" in message
    assert "data.batch_size='abc': expected an integer >= 1" in message
    assert "model.head.drop_path=1.5" in message
    assert not (tmp_path / "checkpoints").exists()  # nothing was built or trained
    results = json.loads((tmp_path / "results.json").read_text())  # for sweep reports
    assert results["status"] == "failed" and "model.optimizer.lr=-0.1" in results["error"]
    cfg = _compose("experiment=smoke", "model.loss.distill.scale=0.5", "model.teacher=null")
    with pytest.raises(ConfigError, match=r"model\.loss\.distill\.scale=0\.5: distillation needs"):
        validate(cfg)
    with pytest.raises(ConfigError, match=r"model\.scheduler\.min_lr=0\.1: expected <= "):
        validate(_compose("experiment=smoke", "model.scheduler.min_lr=0.1"))


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_smoke_experiment_through_the_entry_point(tmp_path):
    """`resireg-train experiment=smoke` end to end in a fresh process."""
    out = tmp_path / "run"
    run("resireg-train", "experiment=smoke", f"hydra.run.dir={out}", "~callbacks.progress_bar",
        timeout=300)  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed" and results["error"] is None
    history = results["history"]
    assert [h["epoch"] for h in history] == list(range(6))
    assert history[-1]["train/loss"] < history[0]["train/loss"] - 0.1, history
    assert results["best"]["train/loss"]["value"] == min(h["train/loss"] for h in history)
    assert results["final"]["data/skipped_invalid"] == 0
    rows = _read_csv(out / "metrics.csv")
    steps = [int(r["step"]) for r in rows if r["train/loss_step"]]
    assert len(steps) == 6 * 8 and steps == sorted(steps)
    assert (out / ".hydra" / "config.yaml").is_file() and (
        out / "checkpoints" / "last.ckpt"
    ).is_file()
    # The export reloads into the same trained weights as the last checkpoint.
    vlm = ResiregVLM.from_pretrained(out / "export")
    module = ResiregModule.load_from_checkpoint(out / "checkpoints" / "last.ckpt")
    assert torch.equal(vlm.head.proj.weight, module.vlm.head.proj.weight)
    image = torch.rand(3, 64, 80)
    torch.testing.assert_close(
        vlm.encode_image(image, resireg="full", n_prototypes=4, n_components=4),
        module.vlm.eval().encode_image(image, resireg="full", n_prototypes=4, n_components=4),
    )
    # OVSS of BB / Lite / Full on the synthetic eval set, every epoch, in [0, 1] ...
    names = [
        f"val/ovss/synthetic/{m}_{v}" for m in ("miou", "fmiou") for v in ("bb", "lite", "full")
    ]
    for row in history:
        assert all(0.0 <= row[n] <= 1.0 for n in names), row
    assert results["best"][names[2]]["value"] == max(h[names[2]] for h in history)
    logged_rows = [r for r in rows if r[names[0]]]
    assert len(logged_rows) == 6 and all(r["step"] for r in logged_rows)
    # ... and resireg-eval recomputes the last epoch's values exactly from the export (the
    # logged values went through float32 tensors).
    recomputed = evaluate_export(out / "export", tmp_path / "eval")
    assert set(recomputed) == set(names)
    assert all(np.float32(recomputed[n]) == np.float32(history[-1][n]) for n in names)


class _CrashAt(L.Callback):
    def __init__(self, epoch):
        self.epoch = epoch

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            raise RuntimeError("simulated crash")


@pytest.mark.slow
def test_resume_reaches_the_uninterrupted_weights_schedule_and_metrics(tmp_path):
    def cfg(name, *extra):
        return _compose("experiment=smoke", f"paths.output_dir={tmp_path / name}",
                        "trainer.max_epochs=3", "data.steps_per_epoch=4",
                        "~callbacks.progress_bar", *extra)  # fmt: skip

    train(cfg("straight"))
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg("resumed"), callbacks=[_CrashAt(2)])
    crashed = json.loads((tmp_path / "resumed" / "results.json").read_text())
    assert crashed["status"] == "failed" and "simulated crash" in crashed["error"]
    assert crashed["epoch"] == 1
    results = train(cfg("resumed", "ckpt_path=last"))
    assert results["status"] == "completed"

    a = torch.load(tmp_path / "straight/checkpoints/last.ckpt", weights_only=False)
    b = torch.load(tmp_path / "resumed/checkpoints/last.ckpt", weights_only=False)
    assert a["global_step"] == b["global_step"] == 12
    assert a["state_dict"].keys() == b["state_dict"].keys()
    # Equal up to float noise: the frozen text tower embeds a caption in a different batch
    # after the resume (its cache starts empty), ~1e-7, carried on by the remaining steps.
    for key in a["state_dict"]:
        torch.testing.assert_close(a["state_dict"][key], b["state_dict"][key], atol=1e-6, rtol=0)
    rows_a = _read_csv(tmp_path / "straight/metrics.csv")
    rows_b = _read_csv(tmp_path / "resumed/metrics.csv")
    assert [(r["step"], r["epoch"], r["train/lr"]) for r in rows_a] == [
        (r["step"], r["epoch"], r["train/lr"]) for r in rows_b
    ]  # no row lost or repeated across the interruption; same schedule
    for key in ("train/loss_step", "train/loss_epoch"):
        va = [float(r[key]) for r in rows_a if r[key]]
        vb = [float(r[key]) for r in rows_b if r[key]]
        assert va == pytest.approx(vb, rel=1e-5, abs=1e-6)
    # The cosine schedule ran over all 12 steps, not restarted at the resume.
    lrs = [float(r["train/lr"]) for r in rows_b if r["train/lr"]]
    assert len(lrs) == 12 and all(x > y for x, y in zip(lrs, lrs[1:], strict=False))
    assert [h["epoch"] for h in results["history"]] == [0, 1, 2]
    # What a sweeper (e.g. Optuna) receives from the Hydra main with optimized_metric set.
    best = results["best"]["train/loss"]["value"]
    assert optimized_value(cfg("x", "optimized_metric=train/loss"), results) == best
    with pytest.raises(KeyError, match="optimized_metric='val/nope'"):
        optimized_value(cfg("x", "optimized_metric=val/nope"), results)


@pytest.mark.slow
def test_without_the_caption_cache_a_resume_is_bitwise_the_uninterrupted_run(tmp_path):
    """The guarantee a resume keeps (issue 22, case 13): with model.text.cache_size=0 each
    batch embeds its own captions, so a run crashed after epoch 0 and resumed ends bit for
    bit where the uninterrupted run does (with the cache it differs at float-rounding level,
    see test_resume_reaches_the_uninterrupted_weights_schedule_and_metrics)."""

    def cfg(name, *extra):
        return _compose("experiment=smoke", f"paths.output_dir={tmp_path / name}",
                        "trainer.max_epochs=2", "data.steps_per_epoch=3",
                        "model.text.cache_size=0", "~callbacks.progress_bar",
                        "~callbacks.resireg_eval", *extra)  # fmt: skip

    train(cfg("straight"))
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg("resumed"), callbacks=[_CrashAt(1)])
    train(cfg("resumed", "ckpt_path=last"))
    a = torch.load(tmp_path / "straight/checkpoints/last.ckpt", weights_only=False)
    b = torch.load(tmp_path / "resumed/checkpoints/last.ckpt", weights_only=False)
    assert a["global_step"] == b["global_step"] == 6
    assert a["state_dict"].keys() == b["state_dict"].keys()
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])


def test_stage2_starts_from_stage1_weights_without_teacher(tmp_path):
    stage1 = tmp_path / "stage1"
    train(_compose("experiment=smoke", f"paths.output_dir={stage1}", "trainer.max_epochs=1",
                   "data.steps_per_epoch=2", "~callbacks.progress_bar"))  # fmt: skip
    ckpt = torch.load(stage1 / "checkpoints/last.ckpt", weights_only=False)["state_dict"]
    stage2 = tmp_path / "stage2"
    cfg = _compose(
        "experiment=smoke", f"paths.output_dir={stage2}", "trainer.max_epochs=1",
        "data.steps_per_epoch=1", "~callbacks.progress_bar", "model.teacher=null",
        "model.loss.distill.scale=0", f"+model.init_from={stage1 / 'checkpoints/last.ckpt'}",
        "model.optimizer.lr=1e-12", "model.scheduler.min_lr=1e-12",
    )  # fmt: skip
    train(cfg)
    after = torch.load(stage2 / "checkpoints/last.ckpt", weights_only=False)["state_dict"]
    assert not any(k.startswith(("teacher.", "distill_head.")) for k in after)
    for key in ("vlm.head.proj.weight", "vlm.text_proj.weight", "logit_scale"):
        torch.testing.assert_close(after[key], ckpt[key], atol=1e-6, rtol=0)  # lr ~ 0
    assert math.isfinite(json.loads((stage2 / "results.json").read_text())["final"]["train/loss"])
    # From an export folder as well (head + text projection).
    module, _ = build(cfg)
    loaded = module.load_trained(stage1 / "export")
    assert "vlm.head.proj.weight" in loaded
    assert torch.equal(module.vlm.head.proj.weight, ckpt["vlm.head.proj.weight"])
    with pytest.raises(FileNotFoundError, match=r"model\.init_from='nope'"):
        module.load_trained("nope")


@pytest.mark.slow
def test_tensorboard_and_mlflow_trackers(tmp_path):
    """`tracker=[tensorboard,mlflow]` adds both trackers; metrics.csv is still written."""
    pytest.importorskip("tensorboard")
    mlflow = pytest.importorskip("mlflow")
    out = tmp_path / "run"
    train(_compose("experiment=smoke", f"paths.output_dir={out}", f"paths.log_dir={tmp_path}",
                   "tracker=[tensorboard,mlflow]", "trainer.max_epochs=1", "data.steps_per_epoch=2",
                   "~callbacks.progress_bar"))  # fmt: skip
    assert (out / "metrics.csv").is_file()
    assert list((out / "tensorboard").glob("events.out.tfevents.*"))
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = mlflow.search_runs(experiment_names=["resireg"], output_format="list")
    assert len(runs) == 1 and runs[0].info.run_name == "smoke"
    assert "train/loss_epoch" in runs[0].data.metrics


class _RecordTokenized(L.Callback):
    """Records every text the frozen text tower tokenizes (i.e. runs on)."""

    def __init__(self):
        self.texts = []

    def on_fit_start(self, trainer, pl_module):
        text = pl_module.vlm.text
        tokenize = text.tokenizer

        def recording(texts):
            self.texts.extend(texts)
            return tokenize(texts)

        text.tokenizer = recording


@pytest.mark.slow
def test_eval_prompts_run_through_the_text_tower_once_per_run_at_the_interval(tmp_path):
    from resireg.ovss import class_prompts
    from resireg_train.data.synthetic import SYNTHETIC_CLASSES

    probe = _RecordTokenized()
    cfg = _compose("experiment=smoke", f"paths.output_dir={tmp_path}", "trainer.max_epochs=5",
                   "data.steps_per_epoch=2", "callbacks.resireg_eval.every_n_epochs=2",
                   "~callbacks.progress_bar")  # fmt: skip
    results = train(cfg, callbacks=[probe])
    # Every 2nd epoch and the last; the other epochs carry no (stale) evaluation values.
    evaluated = [h["epoch"] for h in results["history"] if "val/ovss/synthetic/miou_full" in h]
    assert evaluated == [1, 3, 4]
    prompts = class_prompts(SYNTHETIC_CLASSES)
    counts = {p: 0 for p in prompts}
    for text in probe.texts:
        if text in counts:
            counts[text] += 1
    assert set(counts.values()) == {1}, "a class prompt was embedded more than once"
    assert len(probe.texts) > len(prompts)  # the training captions went through it too


def test_runs_started_in_the_same_second_get_their_own_folders(tmp_path):
    """Three runs started together (a shell loop, a job array) never share a run folder."""
    procs = run_side_by_side(*[
        ("resireg-train", "experiment=smoke", f"paths.log_dir={tmp_path}",
         f"model.optimizer.lr=-{lr}")  # fails at the config check, quickly
        for lr in (1, 2, 3)], check=False, timeout=300, threads=None)  # fmt: skip
    assert [p.returncode != 0 for p in procs] == [True] * 3, [p.stderr[-500:] for p in procs]
    folders = sorted((tmp_path / "smoke").iterdir())
    assert len(folders) == 3, folders
    errors = {json.loads((f / "results.json").read_text())["error"] for f in folders}
    assert len(errors) == 3  # each run recorded its own failure in its own folder


@pytest.mark.slow
def test_sweeps_started_in_the_same_second_get_their_own_sweep_folders(tmp_path, tiny_export):
    """Two `resireg-eval -m` and two `resireg-train -m` started together (issue 22, case 2):
    every sweep folder carries the run id, so no two share one: each eval job writes its own
    results.json and eval.log, and no training job is refused a folder another sweep took
    (each records its own config error, not a FileExistsError)."""

    def command(script, *args):
        return (script, "-m", *args, f"paths.log_dir={tmp_path}")

    evals = [command("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
                     "dataset.size=4", "num_workers=0", "variants=[bb]", f"seed={i}",
                     "batch_size=2,4") for i in (1, 2)]  # fmt: skip
    trains = [command("resireg-train", "experiment=smoke", f"model.optimizer.lr=-{i},-{i}.5")
              for i in (1, 2)]  # fmt: skip
    procs = run_side_by_side(*evals, *trains, check=False, timeout=600, threads=None)
    assert [p.returncode for p in procs[:2]] == [0, 0], [p.stderr[-2000:] for p in procs[:2]]
    for name, seeds in (("eval", {1, 2}), ("smoke", None)):
        sweeps = sorted((tmp_path / name / "multirun").iterdir())
        assert len(sweeps) == 2 and all(re.search(r"_[0-9a-f]{6}$", s.name) for s in sweeps), sweeps
        jobs = [j for s in sweeps for j in sorted(s.iterdir()) if j.is_dir()]
        assert len(jobs) == 4, jobs
        results = [json.loads((j / "results.json").read_text()) for j in jobs]
        if name == "eval":
            assert all(r["status"] == "completed" for r in results)
            for sweep in sweeps:  # a sweep's jobs share its seed; the other sweep's never
                (seed,) = {
                    yaml.safe_load((j / ".hydra" / "config.yaml").read_text())["seed"]
                    for j in sweep.iterdir() if j.is_dir()
                }  # fmt: skip
                seeds.discard(seed)
            assert seeds == set()
            assert all((j / "eval.log").read_text().count("output dir:") == 1 for j in jobs)
        else:
            errors = [r["error"] for r in results]
            assert all("model.optimizer.lr=" in e and "expected a number > 0" in e
                       for e in errors), errors  # fmt: skip


def test_a_new_run_refuses_a_folder_that_holds_another_run(tmp_path):
    """A hand-pointed hydra.run.dir: the second fresh run stops before touching anything,
    so the two never append to one metrics.csv; resuming the folder is allowed."""
    (tmp_path / "results.json").write_text(json.dumps({"name": "smoke", "status": "running"}))
    (tmp_path / "metrics.csv").write_text("step,train/loss\n0,2.5\n")
    cfg = _compose("experiment=smoke", f"paths.output_dir={tmp_path}")
    with pytest.raises(FileExistsError, match=r"already holds a run \('smoke', status 'running'\)"
                       r": resume it with ckpt_path=last"):  # fmt: skip
        train(cfg)
    assert (tmp_path / "metrics.csv").read_text() == "step,train/loss\n0,2.5\n"
    assert json.loads((tmp_path / "results.json").read_text())["status"] == "running"


@pytest.mark.slow
def test_keys_nothing_reads_are_errors_naming_the_known_key(tmp_path, tiny_export):
    """Issue 22, case 8: Hydra's hint after `batchsize=4` is `+batchsize=4`; the added key
    is refused (not silently ignored), with the key the user meant, from the command line
    and from a config file alike; the keys `+` may add (a stage-2 start, a Trainer argument)
    are not."""
    proc = run("resireg-eval", "+batchsize=4", f"model_path={tiny_export}", "dataset=synthetic",
               f"hydra.run.dir={tmp_path / 'eval'}", check=False)  # fmt: skip
    assert proc.returncode == 1
    expected = "batchsize=4: no such key, nothing would read it (did you mean batch_size?)"
    assert expected in proc.stderr, proc.stderr[-2000:]
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert results["status"] == "failed" and expected in results["error"]

    proc = run("resireg-train", "experiment=smoke", "+batchsize=4", "+model.init_from=/x.ckpt",
               "+trainer.detect_anomaly=false", "+model.loss.contrastive.scal=2",
               f"hydra.run.dir={tmp_path / 'train'}", check=False)  # fmt: skip
    error = json.loads((tmp_path / "train" / "results.json").read_text())["error"]
    assert proc.returncode == 1 and error.splitlines()[1:] == [
        "  batchsize=4: no such key, nothing would read it (did you mean data.batch_size?); "
        "set existing keys without +",
        "  model.loss.contrastive.scal=2: no such key, nothing would read it (did you mean "
        "model.loss.contrastive.scale?); set existing keys without +",
    ], error

    experiment = tmp_path / "conf" / "experiment"
    experiment.mkdir(parents=True)
    smoke = (CONFIG_DIR / "experiment" / "smoke.yaml").read_text()
    (experiment / "typo.yaml").write_text(smoke + "\nbatchsize: 4\n")
    proc = run("resireg-train", "--config-dir", tmp_path / "conf", "experiment=typo",
               f"hydra.run.dir={tmp_path / 'file'}", check=False)  # fmt: skip
    assert proc.returncode == 1
    assert "batchsize=4: no such key, nothing would read it (did you mean data.batch_size?)" in (
        proc.stderr
    ), proc.stderr[-2000:]


@pytest.mark.slow
def test_a_run_folder_written_before_the_layout_by_role_still_resumes(tmp_path):
    """tests/data/run_before_layout is a smoke run folder written by the release before the
    modules moved: its stored config names ``resireg_train.ovss.callback.ReSiRegEval``. The
    resume check maps the old class paths (resireg_train.config.moves), so the same command
    resumes it from its checkpoint instead of refusing a changed ``_target_``."""
    fixture = TESTS / "data" / "run_before_layout"
    logs = tmp_path / "logs"
    out = logs / "smoke" / "run"
    shutil.copytree(fixture, out)
    for stored in [*(out / ".hydra").glob("*.yaml"), out / "results.json"]:
        text = stored.read_text().replace("@RUN_DIR@", str(out)).replace("@LOG_DIR@", str(logs))
        stored.write_text(text.replace("@CHECKOUT@", str(CONFIG_DIR.parent)))
    assert "resireg_train.ovss.callback.ReSiRegEval" in (out / ".hydra" / "config.yaml").read_text()
    proc = run("resireg-train", *yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text()),
               "ckpt_path=last", f"hydra.run.dir={out}")  # fmt: skip
    assert "Restored all states from the checkpoint" in proc.stdout + proc.stderr
