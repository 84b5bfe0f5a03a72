"""The LightningModule on tiny models and synthetic scenes."""

import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from resireg.models import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg_train.module import ResiregModule
from resireg_train.synthetic import SyntheticScenes

MEAN, STD = (
    torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1),
    torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1),
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
        "optimizer": {"lr": 2e-3, "weight_decay": 0.05},
        "scheduler": {"min_lr": 1e-5},
        "steps_per_epoch": 8,
    }
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


def test_training_reduces_loss_and_clamps_logit_scale(tmp_path):
    module = _module(
        optimizer={"lr": 3e-3, "weight_decay": 0.05}, logit_scale={"init": 1 / 0.07, "max": 20.0}
    )
    loader = DataLoader(_Scenes(32), batch_size=8, shuffle=False)
    before = [p.clone() for p in module.vlm.backbone.parameters()]
    record = _Record()
    trainer = _trainer(tmp_path, epochs=8, limit_train_batches=4, callbacks=[record])
    trainer.fit(module, loader)
    assert module.logit_scale.exp().item() <= 20.0 + 1e-4  # clamped after every step
    assert all(
        torch.equal(a, b) for a, b in zip(before, module.vlm.backbone.parameters(), strict=True)
    )
    assert np.mean(record.losses[-4:]) < np.mean(record.losses[:4]) - 0.2, record.losses
    assert 0.0 <= trainer.callback_metrics["train/retrieval_i2t_epoch"] <= 1.0


def test_no_weight_decay_on_norms_biases_and_logit_scale(tmp_path):
    module = _module()
    trainer = _trainer(tmp_path, limit_train_batches=1)
    trainer.fit(module, DataLoader(_Scenes(8), batch_size=4))
    opt = trainer.optimizers[0]
    decayed = {id(p) for p in opt.param_groups[0]["params"]}
    assert opt.param_groups[1]["weight_decay"] == 0.0
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
    assert [m.loss_scales(e) for e in (0, 2, 4, 8)] == pytest.approx(
        [(0, 0), (0.5, 0.025), (1, 0.05), (1, 0.1)]
    )
    stage2 = _module(loss={"distill": {"scale": 0.0}}, teacher={"kind": "conv"})
    assert stage2.teacher is None and stage2.distill_head is None


def test_distillation_trains_the_distill_head(tmp_path):
    m = _module(
        teacher={"kind": "conv", "out_dim": 20},
        loss={"distill": {"scale": 0.1, "warmup_epochs": 0}},
    )
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


def test_overfits_a_small_synthetic_set(tmp_path):
    """In-batch image->text retrieval rises far above chance (1/16) within 200 steps."""
    module = _module(
        optimizer={"lr": 3e-3, "weight_decay": 0.0}, scheduler={"min_lr": 3e-3}, steps_per_epoch=2
    )
    loader = DataLoader(_Scenes(32, seed=3), batch_size=16, shuffle=True)
    record = _Record()
    trainer = _trainer(tmp_path, epochs=100, callbacks=[record])
    trainer.fit(module, loader)
    assert trainer.global_step == 200
    accuracy = trainer.callback_metrics["train/retrieval_i2t_epoch"].item()
    assert accuracy >= 0.75, accuracy  # chance is 0.0625
    assert np.mean(record.losses[-10:]) < 0.5 * np.mean(record.losses[:10])
