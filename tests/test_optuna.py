"""Optuna search through Hydra (conf/hparams_search/resireg_optuna.yaml) on the synthetic set:
a failing trial is recorded and the search goes on, the best trial is the best completed job's
score (read back from the jobs' results.json), a second invocation on the same sweep folder
resumes the study without repeating its trials, and resireg-report writes the search's table
and Optuna's plots."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from _run import report, run

optuna = pytest.importorskip("optuna")
pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")

METRIC = "val/ovss/synthetic/miou_full"


def _search(export, sweep, n_trials):
    """An eval-time search of ``n_trials`` in total: alpha and the prototype count, where 5000
    prototypes exceed a batch's points (the job fails with a config error). Up to 3 of a
    batch of 4 trials may fail."""
    return run("resireg-eval", f"model_path={export}", "dataset=synthetic", "dataset.size=4",
               "num_workers=0", "batch_size=2", "full.upscale=1", "full.tau=0.0",
               "hparams_search=resireg_optuna", f"hparams_search.n_trials={n_trials}",
               "full.n_prototypes=choice(3,6,5000)", "full.alpha=interval(1.0,20.0)",
               "hydra.sweeper.max_failure_rate=0.75",
               f"hydra.sweep.dir={sweep}")  # fmt: skip


def _study(sweep):
    return optuna.load_study(study_name="resireg_optuna", storage=f"sqlite:///{sweep}/optuna.db")


def _job_results(sweep):
    return {p.parent.name: json.loads(p.read_text()) for p in sweep.glob("*/results.json")}


@pytest.mark.slow
def test_search_survives_a_failed_trial_resumes_and_is_reported(tmp_path, tiny_export):
    sweep = tmp_path / "sweep"
    _search(tiny_export, sweep, 4)  # exits 0 although a trial failed
    study = _study(sweep)
    trials = study.get_trials()
    states = [t.state.name for t in trials]
    assert len(trials) == 4 and "FAIL" in states and "COMPLETE" in states, states
    # The failed trials are exactly those with more prototypes than points, and their jobs
    # recorded why.
    assert [t.params["full.n_prototypes"] == 5000 for t in trials] == [s == "FAIL" for s in states]
    results = _job_results(sweep)
    assert len(results) == 4
    failed = [r for r in results.values() if r["status"] == "failed"]
    assert len(failed) == states.count("FAIL")
    assert all("n_prototypes=5000" in r["error"] for r in failed)
    # Best trial = the best completed job's score, recomputed from the results.json files.
    done = [r for r in results.values() if r["status"] == "completed"]
    best = max(done, key=lambda r: r["final"][METRIC])
    assert study.best_value == pytest.approx(best["final"][METRIC], rel=1e-12)
    assert study.best_trial.params["full.alpha"] == pytest.approx(best["params"]["full"]["alpha"])

    # A second invocation on the same sweep folder continues the study to 6 trials in total:
    # 2 new jobs; the first 4 trials and their jobs' records are untouched.
    before = {t.number: (t.state, t.value, t.params) for t in trials}
    records = {name: (sweep / name / "results.json").read_text() for name in results}
    _search(tiny_export, sweep, 6)
    trials = _study(sweep).get_trials()
    assert len(trials) == 6
    assert {t.number: (t.state, t.value, t.params) for t in trials if t.number < 4} == before
    seen = [t.params for t in trials[:4]]  # the resumed sampler does not replay the draws
    assert all(t.params not in seen for t in trials[4:]), [t.params for t in trials]
    assert len(_job_results(sweep)) == 6
    assert all(
        (sweep / name / "results.json").read_text() == text for name, text in records.items()
    )

    said = report(sweep)  # resireg-report's main, in this process
    table = pd.read_csv(sweep / "optuna_trials.csv")
    assert list(table["trial"]) == list(range(6))
    assert list(table["state"]) == [t.state.name for t in trials]
    # Every run trial is matched to its own job, a failed one with its error.
    assert table["job"].nunique() == 6
    fails = table[table["state"] == "FAIL"]
    assert (fails["job status"] == "failed").all() and fails["error"].str.contains("5000").all()
    ok = table[table["state"] == "COMPLETE"]
    for _, row in ok.iterrows():
        assert row["value"] == pytest.approx(_job_results(sweep)[row["job"]]["final"][METRIC])
    best = _study(sweep).best_trial
    assert (
        f"Best trial: {best.number}, value {best.value:.4f}" in (sweep / "summary.md").read_text()
    )
    for name in ("optuna_history.png", "optuna_importance.png"):
        assert (sweep / name).stat().st_size > 10_000, name
    assert "optuna_history" in said
    assert not any(math.isnan(v) for v in ok["value"])


@pytest.mark.parametrize("stored", [float("nan"), None, float("inf")])
def test_a_job_scoring_nan_fails_its_trial_instead_of_ending_the_search(stored):
    """optuna 2.10 (the sweeper's pin) raises in `tell` for a NaN value, outside the sweeper's
    per-trial handling: a NaN (or `null` in results.json) score must raise in the job, which the
    sweeper records as a failed trial; a finite score goes back as a float."""
    import optuna
    from omegaconf import OmegaConf

    from resireg_train.cli.task import optimized_value

    cfg = OmegaConf.create({"optimized_metric": "miou_full"})
    with pytest.raises(ValueError, match=r"optimized_metric='miou_full' is .*not finite"):
        optimized_value(cfg, {"final": {"miou_full": stored}})
    assert optimized_value(cfg, {"final": {"miou_full": 0.25}}) == 0.25
    assert optimized_value(cfg, {"best": {"miou_full": {"value": 0.5, "epoch": 2}}}) == 0.5
    study = optuna.create_study()  # why the job must not return NaN (optuna 2.x only)
    if optuna.__version__.startswith("2."):
        with pytest.raises(ValueError, match="returned nan"):
            study.tell(study.ask(), float("nan"))
