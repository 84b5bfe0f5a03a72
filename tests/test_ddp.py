"""DDP on CPU (gloo): the gathered contrastive loss, and a 2-process training run."""

import json
import socket

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from _run import evaluate_export, run
from resireg_train.training.losses import ContrastiveLoss

WORLD = 2


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_loss(rank, port, image, text, scale, out):
    dist.init_process_group(
        "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=WORLD
    )
    try:
        b = image.shape[0] // WORLD
        img = image[rank * b : (rank + 1) * b].clone().requires_grad_(True)
        txt = text[rank * b : (rank + 1) * b].clone().requires_grad_(True)
        loss, logits, targets = ContrastiveLoss()(img, txt, scale)
        loss.backward()
        out[rank] = {"loss": loss.detach(), "grad": img.grad, "logits": logits.detach(),
                     "targets": targets}  # fmt: skip
    finally:
        dist.destroy_process_group()


def test_gathered_loss_equals_single_process_loss_on_the_global_batch():
    torch.manual_seed(0)
    image, text, scale = torch.randn(8, 16), torch.randn(8, 16), torch.tensor(10.0)
    out = mp.Manager().dict()
    mp.spawn(_rank_loss, args=(_free_port(), image, text, scale, out), nprocs=WORLD, join=True)

    img = image.clone().requires_grad_(True)
    loss, logits, targets = ContrastiveLoss()(img, text, scale)
    loss.backward()
    for rank in range(WORLD):
        torch.testing.assert_close(out[rank]["loss"], loss.detach())
        rows = slice(rank * 4, (rank + 1) * 4)
        torch.testing.assert_close(out[rank]["logits"], logits.detach()[rows])
        assert torch.equal(out[rank]["targets"], targets[rows])
        # The local rank keeps the gradient of the global loss w.r.t. its own rows.
        torch.testing.assert_close(out[rank]["grad"], img.grad[rows])


@pytest.mark.slow
def test_ddp_cpu_trains_logs_and_evaluates_sharded(tmp_path):
    """`trainer=ddp_cpu`: 2 spawned processes over gloo, through the real entry point, with the
    default callbacks: rank 0's progress bar must not issue a collective the other rank does
    not (every reduce is explicit and issued by all ranks at the same point)."""
    out = tmp_path / "run"
    # its two ranks run in its process group: a timeout kills them too
    proc = run("resireg-train", "experiment=smoke", "trainer=ddp_cpu", "trainer.max_epochs=2",
               "data.steps_per_epoch=3", f"hydra.run.dir={out}",
               "callbacks.resireg_eval.batch_size=3")  # fmt: skip
    # No metric is logged with sync_dist, on purpose: Lightning's advice is silenced (case 13).
    assert "sync_dist" not in proc.stdout + proc.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed" and [h["epoch"] for h in results["history"]] == [0, 1]
    assert results["history"][-1]["step"] == 6  # 3 steps per epoch on every rank
    assert (out / "metrics.csv").read_text().count("\n") > 6
    assert (out / "export" / "model.safetensors").is_file()
    # Rank 0 runs in a spawned process without Hydra's logging: its epoch lines still reach
    # the run's train.log and the piped stdout, once per epoch.
    for text in ((out / "train.log").read_text(), proc.stdout):
        assert [line.split(" | ")[0].split()[-2:] for line in text.splitlines()
                if " | " in line and "epoch " in line] == [["epoch", "0/1"], ["epoch", "1/1"]]  # fmt: skip
    # Sharded evaluation (each rank half the batches, confusion matrices summed) logs what a
    # single process computes on the exported model (resireg-eval's task, in this process).
    logged = results["history"][-1]
    recomputed = evaluate_export(out / "export", tmp_path / "eval", "batch_size=3")
    assert recomputed and all(np.float32(v) == np.float32(logged[k]) for k, v in recomputed.items())
