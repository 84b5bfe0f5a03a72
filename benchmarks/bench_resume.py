"""How far a run resumed after a kill drifts from an uninterrupted one (docs/benchmarks.md).

    python benchmarks/bench_resume.py [--epochs 6] [--kill-epoch 3] [--out /tmp/resume]

Three smoke runs per text-cache setting: one straight through, one killed with SIGKILL in the
middle of epoch ``--kill-epoch`` (0-based) and resumed with ``ckpt_path=last``; the table gives
the largest absolute difference of any trained tensor (``last.ckpt``'s state dict) between the
two, with the caption cache of the frozen text tower at its default and off
(``model.text.cache_size=0``). Not a speed benchmark: a reproducibility figure.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L


class KillAt(L.Callback):
    """SIGKILL (no clean-up, as ``kill -9`` or a pre-empted node) at batch ``batch`` of
    epoch ``epoch`` of a run that was not resumed."""

    def __init__(self, epoch: int, batch: int = 2) -> None:
        self.epoch, self.batch = epoch, batch

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        fresh = trainer.ckpt_path is None
        if fresh and trainer.current_epoch == self.epoch and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGKILL)


def _train(out: Path, *overrides: str, check: bool = True) -> int:
    exe = shutil.which("resireg-train")
    cmd = [exe] if exe else [sys.executable, "-m", "resireg_train.cli.train"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1",
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent),
                                          os.environ.get("PYTHONPATH", "")])}  # fmt: skip
    proc = subprocess.run([*cmd, "experiment=smoke", f"hydra.run.dir={out}", *overrides],
                          capture_output=True, text=True, env=env)  # fmt: skip
    if check and proc.returncode != 0:
        raise SystemExit(proc.stderr[-3000:])
    return proc.returncode


def _max_difference(a: Path, b: Path) -> float:
    import torch

    sa = torch.load(a, map_location="cpu", weights_only=False)["state_dict"]
    sb = torch.load(b, map_location="cpu", weights_only=False)["state_dict"]
    assert sa.keys() == sb.keys()
    return max(float((sa[k].double() - sb[k].double()).abs().max()) for k in sa)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--kill-epoch", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_resume"))
    args = parser.parse_args()
    common = [f"trainer.max_epochs={args.epochs}", "~callbacks.progress_bar"]
    kill = [
        "+callbacks.kill._target_=bench_resume.KillAt",
        f"+callbacks.kill.epoch={args.kill_epoch}",
    ]
    print("| text cache | max abs difference of trained weights, resumed - straight |")
    print("|---|---|")
    for label, cache in (
        ("default (200,000 captions)", []),
        ("off (cache_size=0)", ["model.text.cache_size=0"]),
    ):
        root = args.out / ("cache" if not cache else "nocache")
        shutil.rmtree(root, ignore_errors=True)
        _train(root / "straight", *common, *cache)
        code = _train(root / "resumed", *common, *cache, *kill, check=False)
        assert code == -signal.SIGKILL, code
        _train(root / "resumed", *common, *cache, *kill, "ckpt_path=last")
        diff = _max_difference(root / "straight/checkpoints/last.ckpt",
                               root / "resumed/checkpoints/last.ckpt")  # fmt: skip
        print(f"| {label} | {diff:.2e} |", flush=True)


if __name__ == "__main__":
    main()
