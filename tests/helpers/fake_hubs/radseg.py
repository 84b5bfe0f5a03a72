"""The fake RADSeg-OVSS/RADSeg hub repository: :data:`FAKE_RADSEG`, ``hubconf.radseg_encoder``
(``RADSegEncoder`` loading ``NVlabs/RADIO`` itself through ``torch.hub``: here the hub cache,
GitHub unreachable; SCRA on the last block, SCGA, ``align_spatial_features_with_language``,
``encode_prompts``); :data:`RADSEG_STANDIN`, a minimal ``radseg_encoder`` that records its
arguments and checks that inputs arrive on the device it was built for (the teacher's per-rank
build); and :func:`radseg_repo`, a local clone of either.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from helpers.fake_hubs.common import write_repo

FAKE_RADSEG = textwrap.dedent(
    '''
    """Fake RADSeg-OVSS/RADSeg hubconf: RADSegEncoder's structure over the fake RADIO."""
    dependencies = ["torch"]

    import torch
    import torch.nn.functional as F
    from torch import nn


    class SelfCorrelatingRecursiveAttn(nn.Module):  # radseg/radseg.py (simplified)
        def __init__(self, orig_attn, device, dim, qk_norm=False, scra_scaling=10):
            super().__init__()
            self.num_heads = orig_attn.num_heads
            self.qkv, self.proj, self.proj_drop = orig_attn.qkv, orig_attn.proj, orig_attn.proj_drop
            self.scra_scaling = scra_scaling

        def forward(self, x, *args, **kwargs):
            b, n, c = x.shape
            q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, -1).permute(2, 0, 3, 1, 4)
            out = F.scaled_dot_product_attention(q, k, v)
            sim = F.normalize(out, dim=-1) @ F.normalize(out, dim=-1).transpose(-1, -2)
            out = torch.softmax(sim * self.scra_scaling, dim=-1) @ v
            return self.proj_drop(self.proj(out.transpose(1, 2).reshape(b, n, c)))


    class RADSegEncoder:
        def __init__(self, device=None, model_version="radio_v3-b", lang_model="siglip2",
                     return_radio_features=True, compile=False, amp=False, predict=False,
                     classes=None, text_query_mode="labels", prediction_thresh=0.0,
                     prompt_denoising_thresh=0.5, scra_scaling=10.0, scga_scaling=10.0,
                     slide_crop=336, slide_stride=224, sam_refinement=False, **sam_args):
            self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
            self.amp = amp
            self.return_radio_features = return_radio_features
            self.model = torch.hub.load("NVlabs/RADIO", "radio_model", version=model_version,
                                        progress=True, skip_validation=True,
                                        adaptor_names=[lang_model, "sam"])
            self.model.eval()
            self.model = self.model.to(self.device)
            self.lang_adaptor = self.model.adaptors[lang_model]
            self.sam_adaptor = self.model.adaptors["sam"]
            self.model.adaptors = None
            last_block = self.model.model.blocks[-1]
            last_block.attn = SelfCorrelatingRecursiveAttn(
                last_block.attn, dim=self.model.model.embed_dim, device=self.device,
                scra_scaling=scra_scaling)
            if predict or sam_refinement:
                raise AssertionError("the adapter must not ask RADSeg for prediction")
            self.predict = predict
            self.slide_stride = slide_stride
            self.slide_crop = slide_crop
            self.scga_scaling = scga_scaling

        def encode_prompts(self, prompts, onehot=True):
            text = self.lang_adaptor.tokenizer(prompts).to(self.device)
            text_features = self.lang_adaptor.encode_text(text)
            text_features /= text_features.norm(dim=-1, keepdim=True)
            return text_features

        def encode_image_to_feat_map(self, rgb_image, orig_img_size=None, return_preds=False,
                                     ignore_label=True):
            if self.slide_crop > 0:
                feat_map = self._sliding_inference(rgb_image)
            else:
                feat_map = self._single_inference(rgb_image)
            return self._self_correlating_global_aggregation(feat_map)

        def align_spatial_features_with_language(self, features, onehot=True):
            b, c, h, w = features.shape
            features = features.permute(0, 2, 3, 1).reshape(b, -1, c)
            out = self.lang_adaptor.head_mlp(features)
            return out.permute(0, 2, 1).reshape(b, -1, h, w)

        def get_nearest_size(self, h, w):
            return self.model.get_nearest_supported_resolution(h, w)

        def _single_inference(self, rgb_image):
            b, _, h, w = rgb_image.shape
            out = self.model(rgb_image).features
            p = self.model.patch_size
            return out.permute(0, 2, 1).reshape(b, -1, h // p, w // p)

        def _sliding_inference(self, img):
            # Two overlapping windows along the width, averaged (the real one tiles a grid).
            p = self.model.patch_size
            gw = img.shape[-1] // p
            half = max(1, gw // 2 + 1)
            left = self._single_inference(img[..., : half * p])
            right = self._single_inference(img[..., (gw - half) * p :])
            out = torch.zeros(*left.shape[:2], left.shape[2], gw)
            count = torch.zeros(1, 1, 1, gw)
            out[..., :half] += left
            out[..., gw - half :] += right
            count[..., :half] += 1
            count[..., gw - half :] += 1
            return out / count

        def _self_correlating_global_aggregation(self, feat_map):
            b, c, h, w = feat_map.shape
            tokens = feat_map.flatten(2).transpose(1, 2)
            sim = F.normalize(tokens, dim=-1) @ F.normalize(tokens, dim=-1).transpose(1, 2)
            sim = (sim - sim.mean()) * self.scga_scaling
            sim[sim < 0] = -torch.inf
            out = torch.softmax(sim, dim=-1) @ tokens
            return out.transpose(1, 2).reshape(b, c, h, w)


    def radseg_encoder(model_version="c-radio_v3-b", lang_model="siglip2", scra_scaling=10.0,
                       scga_scaling=10.0, **kwargs):
        return RADSegEncoder(model_version=model_version, lang_model=lang_model,
                             scra_scaling=scra_scaling, scga_scaling=scga_scaling, **kwargs)
    '''
)


RADSEG_STANDIN = textwrap.dedent(
    """
    dependencies = ["torch"]
    import torch

    class _Encoder:
        # Like RADSegEncoder: a plain object (no .to()) whose modules stay on the
        # device it was built for; inputs must arrive there.
        def __init__(self, model_version, lang_model, slide_crop, device=None, **kw):
            self.device = torch.device(device or "cuda")
            self.calls = {"model_version": model_version, "lang_model": lang_model,
                          "slide_crop": slide_crop, "device": str(self.device)}
            self.proj = torch.nn.Conv2d(3, 40, 16, stride=16).to(self.device)
            self.lang = torch.nn.Conv2d(40, 24, 1).to(self.device)
        def get_nearest_size(self, h, w):
            return (h // 16) * 16, (w // 16) * 16
        def encode_image_to_feat_map(self, rgb):
            assert rgb.device == self.device, (rgb.device, self.device)
            if rgb.device.type != "meta":
                assert rgb.min() >= 0 and rgb.max() <= 1  # RADIO takes [0, 1] RGB
            return self.proj(rgb)
        def align_spatial_features_with_language(self, feat):
            assert feat.device == self.device
            return self.lang(feat)

    def radseg_encoder(model_version="c-radio_v3-b", lang_model="siglip2", **kwargs):
        return _Encoder(model_version, lang_model, **kwargs)
    """
)


def radseg_repo(folder: Path, standin: bool = False) -> str:
    """A local RADSeg-OVSS/RADSeg clone (:data:`FAKE_RADSEG`, or :data:`RADSEG_STANDIN`)."""
    return str(write_repo(folder, {"hubconf.py": RADSEG_STANDIN if standin else FAKE_RADSEG}))
