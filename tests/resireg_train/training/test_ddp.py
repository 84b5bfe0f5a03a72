"""DDP on CPU (gloo): the gathered contrastive loss, a 2-process training run, and two
"nodes" of one process each sharing one run folder as a cluster starts them."""

import contextlib
import json
import os
import socket
import subprocess

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from helpers.paths import TESTS
from helpers.run import _command, evaluate_export, run, started
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


@pytest.mark.slow
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


def _caption_folder(folder, n):
    """An image folder of ``n`` PNGs whose captions are unique (``sample <i>``): one shard
    per file, so that two ranks split them."""
    from PIL import Image

    train = folder / "train"
    train.mkdir(parents=True)
    rows = []
    for i in range(n):
        pixels = np.random.default_rng(i).integers(0, 255, (72, 88, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(train / f"{i}.png")
        rows.append(json.dumps({"file_name": f"{i}.png", "text": f"sample {i}"}))
    (train / "metadata.jsonl").write_text("\n".join(rows) + "\n")
    return folder


def _node_env(node, port, **extra):
    """The environment of node ``node`` of 2 (one process each) as a launcher sets it
    (Lightning's variables: NODE_RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR / MASTER_PORT),
    tests/ importable (the callbacks of helpers/ddp.py)."""
    return {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
            "NODE_RANK": str(node), "WORLD_SIZE": "2", "LOCAL_RANK": "0",
            "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
            **extra}  # fmt: skip


#: Two nodes of one process each (trainer=cpu, DDP over gloo), one smoke epoch.
NODES = ("experiment=smoke", "trainer.devices=1", "+trainer.num_nodes=2",
         "+trainer.strategy=ddp", "trainer.max_epochs=1", "callbacks.resireg_eval.batch_size=3")  # fmt: skip


@pytest.mark.slow
def test_two_nodes_share_one_run_folder_and_split_the_caption_stream(tmp_path):
    """Two "nodes" started as a cluster would (the same command, the same hydra.run.dir,
    NODE_RANK 0 and 1) train the smoke model to the end: the node of global rank 0 alone
    holds the run folder's lock and writes the record; the captions of the epoch (16 unique
    ones, 8 per rank) are disjoint across the ranks and their union is the whole set."""
    captions = _caption_folder(tmp_path / "captions", 16)
    out, seen = tmp_path / "run", tmp_path / "seen"
    data = ("data=stage1", "data.batch_size=4", "data.steps_per_epoch=4", "data.crop_size=64",
            "data.min_image_size=32", "data.num_workers=0", "data.shuffle_buffer=0",
            "data.pin_memory=false", f"data.sources.textcaps.path={captions}",
            "~data.sources.textcaps.name", "data.sources.textcaps.image=image",
            "data.sources.textcaps.caption=text", "data.sources.textcaps.probability=1.0",
            "~data.sources.localized_narratives", "~data.sources.coco_caption",
            "~data.sources.pexels")  # fmt: skip
    args = [*NODES, *data, "+callbacks.seen._target_=helpers.ddp.SeenCaptions",
            f"+callbacks.seen.folder={seen}", f"hydra.run.dir={out}"]  # fmt: skip
    port = _free_port()
    with contextlib.ExitStack() as stack:
        nodes = [stack.enter_context(started(_command("resireg-train", args), threads=1,
                                             env=_node_env(k, port), stderr=subprocess.PIPE))
                 for k in (0, 1)]  # fmt: skip
        codes = [node.wait(600) for node in nodes]
    assert codes == [0, 0], [n.stderr[-3000:] for n in nodes]
    assert "in use by another job" not in nodes[1].stderr
    assert (out / ".run.lock").read_text().strip() == str(nodes[0].pid)
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed" and [h["epoch"] for h in results["history"]] == [0]
    assert results["history"][-1]["step"] == 4
    assert (out / "export" / "model.safetensors").is_file()
    per_rank = [json.loads((seen / f"seen-{rank}.json").read_text()) for rank in (0, 1)]
    assert [r["world_size"] for r in per_rank] == [2, 2]
    first, second = (r["seen"]["0"] for r in per_rank)
    assert len(first) == len(second) == 8  # 4 steps of 2 (the global batch of 4 split)
    assert set(first).isdisjoint(second)
    assert sorted(first + second) == sorted(f"sample {i}" for i in range(16))


def test_a_node_rank_beyond_the_node_count_is_refused_before_any_work(tmp_path):
    """NODE_RANK=2 of trainer.num_nodes=2: refused in one line naming the variable and the
    setting, before the run folder is created (nothing waits in a rendezvous)."""
    out = tmp_path / "run"
    proc = run("resireg-train", *NODES, f"hydra.run.dir={out}", check=False,
               env=_node_env(2, _free_port()), timeout=120)  # fmt: skip
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert lines == [
        "resireg-train: refused: this process's cluster environment contradicts the trainer: "
        "NODE_RANK=2: this node's rank is not below trainer.num_nodes=2 (node ranks run "
        "0..1); start it with a rank the job has, or set trainer.num_nodes to the job's node "
        "count"
    ], proc.stderr
    assert not out.exists()


_RANK_VARIABLES = ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "LOCAL_WORLD_SIZE",
                   "SLURM_PROCID", "JSM_NAMESPACE_RANK")  # fmt: skip


@pytest.mark.parametrize(("env", "per_node", "rank"), [
    ({}, None, 0),
    ({"NODE_RANK": "1", "LOCAL_RANK": "0"}, None, 1),  # node 1 of 2 one-process nodes
    ({"NODE_RANK": "1", "LOCAL_RANK": "1"}, 4, 5),  # trainer.devices=4
    ({"GROUP_RANK": "2", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}, None, 5),
    ({"RANK": "6", "LOCAL_RANK": "0", "NODE_RANK": "3"}, 2, 6),  # torchrun's RANK first
    ({"SLURM_PROCID": "3"}, None, 3),  # srun's task
    ({"SLURM_PROCID": "0", "LOCAL_RANK": "1"}, 2, 1),  # Lightning re-launched it in a SLURM step
    ({"JSM_NAMESPACE_RANK": "2"}, None, 2),
])  # fmt: skip
def test_the_global_rank_comes_from_the_cluster_environment(monkeypatch, env, per_node, rank):
    """Every launcher's variables give the global rank (by hand: node rank * processes per
    node + local rank); LOCAL_RANK alone no longer makes every node's first process rank 0."""
    from resireg_train.config.machine import process_rank

    for name in _RANK_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    assert process_rank(per_node) == rank
