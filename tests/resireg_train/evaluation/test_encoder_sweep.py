"""ReSiReg across encoders: the encoder config group, the encoder factory, and the Table 1
sweep as a real multirun with its report."""

import json
import math

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from helpers.paths import TESTS
from helpers.run import report, run
from resireg.errors import ConfigError
from resireg.models import ENCODERS, build_encoder
from resireg.specs.encoders import ENCODER_SPECS
from resireg_train.checks.eval import sweep_config_errors, validate_eval
from resireg_train.config.paths import CONFIG_DIR

TEST_CONF = TESTS / "conf"


def test_every_encoder_config_names_a_known_kind_and_builds_its_class_arguments():
    import inspect

    assert set(ENCODER_SPECS) == set(ENCODERS)  # the factory reads the table's kinds
    names = sorted(p.stem for p in (CONFIG_DIR / "encoder").glob("*.yaml"))
    assert sorted(ENCODER_SPECS.all_configs()) == names  # the table names every conf/encoder/ file
    sweep = OmegaConf.load(CONFIG_DIR / "sweep" / "table1.yaml")
    assert sorted(sweep.hydra.sweeper.params.encoder.split(",")) == names
    assert sweep_config_errors(CONFIG_DIR) == []  # the config check agrees
    for name in names:
        with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("eval", overrides=[f"encoder={name}", "model_path=x"])
        validate_eval(cfg)
        spec = OmegaConf.to_container(cfg.encoder, resolve=True)
        builder = ENCODERS[spec["kind"]]
        accepted = set(inspect.signature(builder).parameters)
        keys = set(spec) - {"name", "third_party", "kind"}
        assert keys <= accepted, (name, keys - accepted)  # every key is an argument


def test_resireg_vlm_needs_a_model_path_and_unknown_kinds_are_named():
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval")
        clip = compose("eval", overrides=["encoder=clip_vit_b16"])
    with pytest.raises(ConfigError, match=r"model_path=None: encoder=resireg_vlm needs"):
        validate_eval(cfg)
    validate_eval(clip)  # other encoders need no model_path
    with pytest.raises(ValueError, match=r"^kind='sam': expected one of"):
        build_encoder("sam")


@pytest.mark.slow
def test_table1_sweep_of_two_tiny_encoders_reports_deltas_and_means(tmp_path, tiny_export):
    """`resireg-eval sweep=table1` as a real multirun (2 encoders x the synthetic set, BB /
    Calib / Lite / Full), then `resireg-report`: every delta and mean equals the one
    recomputed from the jobs' results.json. (open_clip's 7 simple templates, not the
    protocol's 80: the CLIP ViT-B/16 text tower on 8 x 80 prompts was 74 s of this test's 84.)"""
    logs = tmp_path / "logs"
    run("resireg-eval", "sweep=table1", "encoder=tiny_vlm,tiny_clip", "dataset=synthetic",
        "dataset.size=4", "dataset.short_side=48", "dataset.templates=simple_imagenet",
        "full.n_prototypes=4", "num_workers=0",
        f"model_path={tiny_export}", f"paths.log_dir={logs}",
        f"hydra.searchpath=[file://{TEST_CONF}]")  # fmt: skip
    (sweep,) = (logs / "table1" / "multirun").iterdir()
    said = report(sweep)  # resireg-report's main, in this process
    assert "2 jobs, 2 completed" in said and "table1_md" in said

    results = {}
    for job in sorted(p for p in sweep.iterdir() if (p / "results.json").is_file()):
        r = json.loads((job / "results.json").read_text())
        assert r["protocol"]["settings"]["templates"] == "open_clip SIMPLE_IMAGENET_TEMPLATES (7)"
        assert r["status"] == "completed" and r["params"]["variants"] == [
            "bb",
            "calib",
            "lite",
            "full",
        ]
        results[r["encoder"]["name"]] = r
    assert set(results) == {"tiny_vlm", "tiny_clip"}
    assert (
        results["tiny_clip"]["encoder"]["parameters"] > results["tiny_vlm"]["encoder"]["parameters"]
    )

    table = pd.read_csv(sweep / "table1.csv")
    rows = table.set_index("encoder")
    deltas = {m: [] for m in ("Calib", "Lite", "Full")}
    third = {m: [] for m in deltas}
    for name, r in results.items():
        final = r["final"]
        bb = final["val/ovss/synthetic/miou_bb"]
        assert rows.loc[name, "synthetic BB"] == pytest.approx(100 * bb)
        assert rows.loc[name, "parameters (M)"] == round(r["encoder"]["parameters"] / 1e6, 1)
        for method in deltas:
            value = final[f"val/ovss/synthetic/miou_{method.lower()}"]
            delta = 100 * (value - bb)
            assert rows.loc[name, f"synthetic {method}"] == pytest.approx(100 * value)
            assert rows.loc[name, f"synthetic {method} Δ"] == pytest.approx(delta)
            deltas[method].append(delta)
            if r["encoder"]["third_party"]:
                third[method].append(delta)
    for method in deltas:
        everyone = rows.loc["mean Δ, all encoders", f"synthetic {method} Δ"]
        assert everyone == pytest.approx(sum(deltas[method]) / 2)
        only = rows.loc["mean Δ, third-party encoders", f"synthetic {method} Δ"]
        assert only == pytest.approx(third[method][0])  # tiny_clip is the only third party
    text = (sweep / "table1.md").read_text()
    assert "| tiny_clip" in text and "no (ours)" in text and "Mean Δ per method" in text


def test_encoder_table_marks_jobs_that_did_not_complete(tmp_path):
    """A failed job leaves its encoder's cells empty and says why; means skip it."""
    from resireg_train.report import Job, encoder_table

    def job(n, encoder, third, status, bb=None, full=None):
        final = (
            {} if bb is None else {"val/ovss/ade20k/miou_bb": bb, "val/ovss/ade20k/miou_full": full}
        )
        results = {"status": status, "final": final,
                   "encoder": {"name": encoder, "third_party": third, "parameters": 5_000_000},
                   "params": {"dataset": {"name": "ade20k"}}}  # fmt: skip
        return Job(tmp_path / str(n), n, {"encoder": encoder, "dataset": "ade20k"}, results)

    jobs = [job(0, "a", True, "completed", 0.30, 0.36), job(1, "b", True, "failed"),
            job(2, "ours", False, "completed", 0.40, 0.41)]  # fmt: skip
    table = encoder_table(jobs).set_index("encoder")
    assert table.loc["b", "ade20k status"] == "failed"
    assert math.isnan(table.loc["b", "ade20k Full Δ"])
    assert table.loc["a", "ade20k Full Δ"] == pytest.approx(6.0)
    assert table.loc["mean Δ, all encoders", "ade20k Full Δ"] == pytest.approx((6.0 + 1.0) / 2)
    assert table.loc["mean Δ, third-party encoders", "ade20k Full Δ"] == pytest.approx(6.0)
