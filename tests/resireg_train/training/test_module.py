"""The LightningModule on tiny models and synthetic scenes."""

import functools

import lightning as L
import numpy as np
import pytest
import torch
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch.utils.data import DataLoader

from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg_train.data.synthetic import SyntheticScenes
from resireg_train.training.module import ResiregModule

MEAN, STD = (
    torch.tensor(IMAGENET_DEFAULT_MEAN).view(3, 1, 1),
    torch.tensor(IMAGENET_DEFAULT_STD).view(3, 1, 1),
)


class _Scenes(torch.utils.data.Dataset):
    def __init__(self, n, seed=0):
        self.scenes = SyntheticScenes(size=n, image_size=(64, 64), seed=seed)

    def __len__(self):
        return len(self.scenes)

    def __getitem__(self, i):
        s = self.scenes[i]
        image = torch.from_numpy(np.asarray(s["image"]).copy()).permute(2, 0, 1).float() / 255
        return {"image": (image - MEAN) / STD, "caption": s["caption"]}


def _module(**kw):
    cfg = {
        "backbone": TINY_BACKBONE,
        "head": TINY_HEAD,
        "text": TINY_TEXT,
        "optimizer": functools.partial(torch.optim.AdamW, lr=2e-3, weight_decay=0.05),
        "scheduler": {"min_lr": 1e-5},
        "steps_per_epoch": 8,
        "teacher": None,
        "loss": {"contrastive": {"scale": 1.0, "warmup_epochs": 0},
                 "distill": {"scale": 0.0, "warmup_epochs": 0}},
        "logit_scale": {"init": 1 / 0.07, "max": 100.0},
    }  # fmt: skip
    cfg.update(kw)
    return ResiregModule(**cfg)


def _trainer(tmp_path, epochs=1, **kw):
    return L.Trainer(
        max_epochs=epochs, accelerator="cpu", logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path, **kw,
    )  # fmt: skip


class _Record(L.Callback):
    def __init__(self):
        self.losses = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))


class _RecordScale(L.Callback):
    def __init__(self):
        self.scales = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        self.scales.append(module.logit_scale.exp().item())  # after the previous step's clamp


@pytest.mark.slow
def test_training_reduces_loss_and_clamps_logit_scale(tmp_path):
    # The clamp (12) lies below the initial scale (1/0.07 = 14.3), which training alone
    # keeps near 14: without the clamp every recorded scale would exceed 12.
    module = _module(
        optimizer=functools.partial(torch.optim.AdamW, lr=3e-3, weight_decay=0.05),
        logit_scale={"init": 1 / 0.07, "max": 12.0},
    )
    loader = DataLoader(_Scenes(32), batch_size=8, shuffle=False)
    before = [p.clone() for p in module.vlm.backbone.parameters()]
    record, scale = _Record(), _RecordScale()
    trainer = _trainer(tmp_path, epochs=8, limit_train_batches=4, callbacks=[record, scale])
    trainer.fit(module, loader)
    assert scale.scales[0] == pytest.approx(1 / 0.07)  # the initial scale, before any step
    assert max(scale.scales[1:]) <= 12.0 + 1e-5  # clamped after every step ...
    assert scale.scales[1] == pytest.approx(12.0, abs=1e-5)  # ... and hit after the first
    assert all(
        torch.equal(a, b) for a, b in zip(before, module.vlm.backbone.parameters(), strict=True)
    )
    assert np.mean(record.losses[-4:]) < np.mean(record.losses[:4]) - 0.2, record.losses


def test_retrieval_accuracy_is_in_batch_image_to_text_top1():
    module = _module().eval()
    batch = next(iter(DataLoader(_Scenes(8, seed=2), batch_size=8)))
    with torch.no_grad():
        _, logs = module.losses(batch, step=0)
        image = torch.nn.functional.normalize(module.vlm.encode(batch["image"]).embedding, dim=1)
        text = torch.nn.functional.normalize(module.vlm.text_embedding(batch["caption"]), dim=1)
    expected = ((image @ text.T).argmax(1) == torch.arange(8)).float().mean()
    assert logs["train/retrieval_i2t"].item() == expected.item()
    # A permutation of the captions changes which caption each image should find.
    with torch.no_grad():
        _, shuffled = module.losses({**batch, "caption": batch["caption"][::-1]}, step=0)
    reversed_hits = ((image @ text.flip(0).T).argmax(1) == torch.arange(8)).float().mean()
    assert shuffled["train/retrieval_i2t"].item() == reversed_hits.item()


def test_no_weight_decay_on_norms_biases_and_logit_scale(tmp_path):
    module = _module()
    trainer = _trainer(tmp_path, limit_train_batches=1)
    trainer.fit(module, DataLoader(_Scenes(8), batch_size=4))
    opt = trainer.optimizers[0]
    groups = {g["weight_decay"]: g["params"] for g in opt.param_groups}
    assert set(groups) == {0.0, 0.05}
    decayed = {id(p) for p in groups[0.05]}
    assert id(module.logit_scale) not in decayed
    names = {id(p): n for n, p in module.named_parameters()}
    assert all(names[i].endswith("weight") and "norm" not in names[i] for i in decayed)
    assert all(not n.startswith(("vlm.backbone", "vlm.text.")) for n in map(names.get, decayed))


def test_loss_scales_follow_warmup_and_distill_only_in_stage1():
    m = _module(
        teacher={"kind": "conv", "out_dim": 20},
        loss={
            "contrastive": {"scale": 1.0, "warmup_epochs": 4},
            "distill": {"scale": 0.1, "warmup_epochs": 8},
        },
    )
    scales = [s for e in (0, 2, 4, 8) for s in m.loss_scales(e)]
    assert scales == pytest.approx([0, 0, 0.5, 0.025, 1, 0.05, 1, 0.1])
    stage2 = _module(teacher={"kind": "conv"})  # distill.scale 0
    assert stage2.teacher is None and stage2.distill_head is None


def test_distillation_trains_the_distill_head(tmp_path):
    m = _module(
        teacher={"kind": "conv", "out_dim": 20},
        loss={
            "contrastive": {"scale": 1.0, "warmup_epochs": 0},
            "distill": {"scale": 0.1, "warmup_epochs": 0},
        },
    )
    assert m.distill_head is None  # built with the teacher, on the rank's device, in setup
    m.setup("fit")
    w0 = m.distill_head.weight.clone()
    trainer = _trainer(tmp_path, limit_train_batches=2)
    trainer.fit(m, DataLoader(_Scenes(8), batch_size=4))
    assert "train/loss_distill_step" in trainer.callback_metrics
    assert not torch.equal(w0, m.distill_head.weight)


def test_non_finite_loss_stops_with_step(tmp_path):
    m = _module()
    with torch.no_grad():
        m.vlm.text_proj.weight.fill_(float("nan"))
    with pytest.raises(FloatingPointError, match="global step 0"):
        _trainer(tmp_path, limit_train_batches=1).fit(m, DataLoader(_Scenes(4), batch_size=4))


def test_checkpoint_excludes_frozen_parts(tmp_path):
    m = _module()
    trainer = _trainer(tmp_path, limit_train_batches=1)
    trainer.fit(m, DataLoader(_Scenes(4), batch_size=4))
    trainer.save_checkpoint(tmp_path / "a.ckpt")
    sd = torch.load(tmp_path / "a.ckpt", weights_only=False)["state_dict"]
    assert any(k.startswith("vlm.head.") for k in sd)
    assert not any(k.startswith(("vlm.backbone.", "vlm.text.")) for k in sd)
    restored = ResiregModule.load_from_checkpoint(tmp_path / "a.ckpt")
    assert torch.equal(restored.vlm.head.proj.weight, m.vlm.head.proj.weight)


@pytest.mark.slow
def test_overfits_a_small_synthetic_set(tmp_path):
    """In-batch image->text retrieval rises far above chance (1/16) within 200 steps."""
    module = _module(
        optimizer=functools.partial(torch.optim.AdamW, lr=3e-3, weight_decay=0.0),
        scheduler={"min_lr": 3e-3},
        steps_per_epoch=2,
    )
    loader = DataLoader(_Scenes(32, seed=3), batch_size=16, shuffle=True)
    record = _Record()
    trainer = _trainer(tmp_path, epochs=100, callbacks=[record])
    trainer.fit(module, loader)
    assert trainer.global_step == 200
    accuracy = trainer.callback_metrics["train/retrieval_i2t_epoch"].item()
    assert accuracy >= 0.75, accuracy  # chance is 0.0625
    assert np.mean(record.losses[-10:]) < 0.5 * np.mean(record.losses[:10])
