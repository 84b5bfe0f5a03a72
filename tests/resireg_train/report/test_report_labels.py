"""Report readability on an Optuna-style training sweep: curves.png's legend names the varying
parameters in short form, and summary.md shows log-scale values in significant digits."""

from __future__ import annotations

import json

import yaml

from resireg_train.report import collect, report
from resireg_train.report.figures import curves_figure, short_keys, short_value

LRS = [0.000646628492, 0.00123456789, 0.0000251189]
SCALES = [0.0123456, 0.4, 0.25]


def _sweep(tmp_path):
    sweep = tmp_path / "stage1_optuna"
    for n, (lr, scale) in enumerate(zip(LRS, SCALES, strict=True)):
        overrides = {"model.optimizer.lr": repr(lr), "model.loss.distill.scale": repr(scale),
                     "model.loss.contrastive.scale": "1.0" if n else "0.5"}  # fmt: skip
        folder = sweep / f"{n}_trial"
        (folder / ".hydra").mkdir(parents=True)
        (folder / ".hydra" / "overrides.yaml").write_text(
            yaml.safe_dump([f"{k}={v}" for k, v in overrides.items()])
        )
        history = [{"epoch": e, "step": e, "train/loss": 2.0 - 0.1 * e - n} for e in range(3)]
        (folder / "results.json").write_text(json.dumps(
            {"name": "stage1_optuna", "status": "completed", "history": history,
             "final": {"train/loss": history[-1]["train/loss"]},
             "best": {"train/loss": {"value": history[-1]["train/loss"], "epoch": 2}}}))  # fmt: skip
    return sweep


def test_short_keys_and_values():
    keys = ["model.optimizer.lr", "model.loss.distill.scale", "model.loss.contrastive.scale"]
    assert short_keys(keys) == {"model.optimizer.lr": "lr",
                                "model.loss.distill.scale": "distill.scale",
                                "model.loss.contrastive.scale": "contrastive.scale"}  # fmt: skip
    assert short_value("0.000646628492") == "0.000647" and short_value("ade20k") == "ade20k"
    assert short_value("24") == "24"


def test_curves_legend_and_summary_are_readable(tmp_path):
    sweep = _sweep(tmp_path)
    fig = curves_figure(collect(sweep), "train/loss")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == [
        "contrastive.scale=0.5, distill.scale=0.0123, lr=0.000647",
        "contrastive.scale=1, distill.scale=0.4, lr=0.00123",
        "contrastive.scale=1, distill.scale=0.25, lr=2.51e-05",
    ]
    summary = report(sweep, tmp_path / "out", "train/loss")["md"].read_text()
    rows = [[c.strip() for c in line.split("|")[1:-1]]
            for line in summary.splitlines() if line.startswith("|")][2:]  # fmt: skip
    # the varying overrides in 4 significant digits (0.0006466 read 0.0006 before), the scores
    # at 4 decimals
    assert rows[0] == ["0", "0.5", "0.01235", "0.0006466", "completed", "1.8000", "1.8000", "2", ""]
    assert rows[2][3] == "2.512e-05" and rows[2][5] == "-0.2000"
