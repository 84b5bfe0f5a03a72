"""Cost of a pruned against an unpruned Optuna search (``hparams_search=stage1_optuna`` on the
smoke experiment, CPU): the same seeded search (same sampler seed, same trials drawn while no
trial is pruned) run twice, once with the stage-1 median pruner and once with
``hydra.sweeper.pruner=null``; reported: trials, epochs trained (from each trial's reported
epochs, read back from the study), wall time, and the ratios.

    python benchmarks/bench_search.py [--trials 6] [--epochs 3] [--out /tmp/bench_search]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def search(sweep: Path, trials: int, epochs: int, pruner: list[str]) -> float:
    """Run one search; returns its wall time in seconds."""
    command = [
        sys.executable, "-m", "resireg_train.cli.train", "experiment=smoke",
        "hparams_search=stage1_optuna", f"hparams_search.n_trials={trials}",
        f"trainer.max_epochs={epochs}", "model.scheduler.min_lr=1.0e-8",
        # a range in which some learning rates cannot learn in a few epochs
        "model.optimizer.lr=tag(log,interval(1.0e-7,3.0e-3))",
        "hydra.sweeper.sampler.n_startup_trials=100",  # random draws: the same in both runs
        f"hydra.sweep.dir={sweep}", *pruner,
    ]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, cwd=ROOT)
    return time.perf_counter() - start


def epochs_run(sweep: Path) -> tuple[int, dict[str, int]]:
    """Epochs trained over the study's trials, and the trials per state."""
    from resireg_train.search.storage import load_study

    study = load_study(sweep, None, "stage1_optuna")
    states: dict[str, int] = {}
    for trial in study.get_trials():
        states[trial.state.name] = states.get(trial.state.name, 0) + 1
    return sum(len(t.intermediate_values) for t in study.get_trials()), states


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=6)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_search"))
    args = parser.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    runs = {
        "unpruned": ["hydra.sweeper.pruner=null"],
        # the stage-1 median pruner, its start-up and warm-up scaled to this short search
        "pruned": ["hydra.sweeper.pruner.n_startup_trials=2", "hydra.sweeper.pruner.n_warmup_steps=0"],
    }  # fmt: skip
    rows = {}
    for name, pruner in runs.items():
        wall = search(args.out / name, args.trials, args.epochs, pruner)
        rows[name] = (wall, *epochs_run(args.out / name))
    print(f"{args.trials} trials x {args.epochs} epochs, experiment=smoke, CPU")
    print(f"{'search':>9} | {'epochs trained':>14} | {'wall s':>7} | trials per state")
    for name, (wall, epochs, states) in rows.items():
        print(f"{name:>9} | {epochs:>14} | {wall:7.1f} | {states}")
    (wu, eu, _), (wp, ep, _) = rows["unpruned"], rows["pruned"]
    print(f"pruned / unpruned: epochs {ep / eu:.2f}, wall time {wp / wu:.2f}")


if __name__ == "__main__":
    main()
