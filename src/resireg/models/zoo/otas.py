"""OTAS (Schwaiger et al., "OTAS: Open-vocabulary Token Alignment for Outdoor Segmentation",
arXiv 2507.08851, ICRA 2026) as a :class:`DenseEncoder`: a backbone-only reference.

OTAS is training-free and has no weights of its own: its public release
(https://github.com/SimonSchwaiger/otas, ``src/model.py``, ``src/vision_utils.py``,
``src/config.py``, ``src/model_config/OTAS_small.json``,
``src/foundation_models/maskclip_onnx/{model,interpolate}.py``) composes two public models:
DINOv2 ViT-S/14 with 4 registers (``dinov2_vits14_reg4_pretrain.pth``, the checkpoint of
``torch.hub`` ``facebookresearch/dinov2`` ``dinov2_vits14_reg``) and OpenAI CLIP ViT-B/16
(``ViT-B-16.pt``, run through the value path of RogerQi's ``maskclip_onnx`` port of
MaskCLIP, which drops the last block's residual and MLP). What its single-view embedding
(``language_map.embed_image``, with the ``OTAS_small.json`` configuration that its
``inference.single_inference`` loads by default) does to one image, and therefore this
adapter, per image of the batch:

1. **DINOv2** (``OTASFeaturizer.dinov2_pipe``): the image resized to
   ``dino_input_size`` x ``dino_input_size`` (224; bilinear), ImageNet mean / std,
   ``forward_features(x)["x_norm_patchtokens"]`` ``[g*g, 384]`` (``g = 16``). OTAS builds the
   ViT from its own copy of DINOv2's ``vision_transformer.py`` with the constructor defaults
   ``interpolate_antialias=False, interpolate_offset=0.1``, whereas the hub entry point sets
   ``True, 0.0``; the positional embedding (37 x 37) is interpolated to 16 x 16, so the two
   differ, and this adapter sets the hub model's two attributes to OTAS's values.
2. **Clustering** (``dino_upscaled_feat``, ``_dim_reduction``, ``_cluster_model``,
   ``_segmentation_map``): patch tokens L2-normalised, upsampled bilinearly by
   ``dino_scale_factor`` (1), flattened row-major; PCA fitted on this image alone
   (``TorchPCA``: centred, ``torch.linalg.svd``, the first ``n_components`` = 12 right
   singular vectors), projections L2-normalised; scikit-learn ``KMeans(n_clusters=24,
   random_state=0)`` (``cluster_model_type="kmeans"``; defaults ``k-means++``, one
   initialisation, 300 iterations, ``tol=1e-4``, Lloyd) gives one label per token; the label
   map is resized (nearest) to ``shared_feat_resolution`` x ``shared_feat_resolution`` (16).
3. **CLIP dense tokens** (``clip_pipe``, ``maskclip_onnx``): the image's shorter side resized to
   ``clip_input_size`` (224, aspect kept: ``transforms.Resize(224)``) and normalised with the
   **ImageNet** mean / std (OTAS's ``t_clip``, not CLIP's own); conv stem (a remainder of
   fewer than 16 pixels is dropped), class token, positional embedding interpolated to the
   ``(H/16, W/16)`` grid (bicubic, ``scale_factor=((H/16 + 0.1) / 14, (W/16 + 0.1) / 14)``,
   no antialiasing; left as is for a 14 x 14 grid of a square image), ``ln_pre``, all blocks
   but the last, then the last block's value path ``out_proj(V(ln_1(x)))`` (no attention,
   residual or MLP: ``maskclip_onnx/model.py``, ``ResidualAttentionBlock.forward_v``, whose
   comment says adding the residual or the MLP degrades the result), ``ln_post``, ``proj``
   -> ``[512, H/16, W/16]``. This is ``dense_path="value"`` (the default);
   ``dense_path="maskclip"`` keeps the residual and the MLP as the official MaskCLIP code
   does (:class:`~resireg.models.zoo.clip.ClipEncoder`), a departure from OTAS.
4. **Shared grid** (``clip_shared_feat_map``): the CLIP map is sampled onto the square
   ``S x S`` grid (``S = shared_feat_resolution``) by nearest lookup, row ``i`` <- source row
   ``floor(i * H_src / S)`` (column likewise).
5. **Hard-mask pooling** (``masked_average_pooling``): for every cluster, the mean of the
   (raw) CLIP features of its cells, L2-normalised, is written to each of its cells ->
   ``[512, S, S]``: OTAS's dense language features.
6. **Queries** (``clip_encode_text``): ``clip.tokenize`` + CLIP's ``encode_text``,
   compared by cosine similarity (``clip_similarity``); here :class:`ClipEncoder`'s open_clip
   text tower of the same model (same BPE, start / end tokens and end-token pooling).

This adapter's :class:`DenseOutput`, from one DINOv2 pass and one CLIP pass per batch:

- ``intermediates`` ``[B, 384, H/14, W/14]``: the DINOv2 patch tokens of step 1 (final
  norm, not normalised), bilinearly resized from 16 x 16 to the canvas grid,
- ``language`` ``[B, 512, h, w]``: the pooled map of step 5. With ``output_grid="canvas"``
  (default) it is resized bilinearly (``align_corners=False``) from ``S x S`` to the canvas
  grid ``(H/14, W/14)``: OTAS resizes its ``S x S`` similarity maps bilinearly to the image
  (``single_inference.similarity_single``), and since the pooled features are unit norm,
  interpolating the features then taking cosines with unit-norm queries equals interpolating
  the similarities up to a positive factor per pixel, so the per-pixel argmax is OTAS's at
  those positions. ``output_grid="shared"`` returns the ``S x S`` map itself.
- ``embedding`` ``[B, 512]``: CLIP's image embedding (class token, ``ln_post``, ``proj``)
  from the same CLIP pass, i.e. OTAS's ``clip_pipe_global_token``.

The canvas (ImageNet mean / std, sides multiples of 14) stands in for OTAS's PIL image:
both resizes start from it (bilinear with antialiasing on the normalised tensor), so they
equal OTAS's exactly only when the canvas is the original image and needs no resizing.
Everything runs in float32; OTAS runs under autocast (``enable_amp_autocast``; CLIP's
weights in half precision on a GPU), so values differ at that precision. OTAS's query-time
steps are not part of the dense features and are left out: subtracting negative prompts,
the per-prompt min-max rescaling of a similarity map, thresholding, and SAM 2 mask
refinement.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch import Tensor

from resireg.errors import ConfigError, arguments_under, parameters
from resireg.models.frozen import FrozenModule
from resireg.models.hub import PINNED_REFS, check_hub_source, hub_target, require_hub_checkpoints
from resireg.models.images import tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule
from resireg.models.zoo.clip import CLIP_MODELS, ClipEncoder, check_dense_path, require_clip_weights

__all__ = ["OTAS_ENTRY_POINT", "OTAS_CHECKPOINTS", "OtasEncoder"]

#: The torch.hub entry point (facebookresearch/dinov2) of OTAS's DINOv2 ViT-S/14 reg4.
OTAS_ENTRY_POINT = "dinov2_vits14_reg"

#: Entry point -> the checkpoint it fetches with ``torch.hub.load_state_dict_from_url``
#: (kept in ``<torch.hub.get_dir()>/checkpoints``); OTAS's ``download_checkpoints.sh``
#: downloads the same file.
OTAS_CHECKPOINTS = {OTAS_ENTRY_POINT: "dinov2_vits14_reg4_pretrain.pth"}

_WEIGHTS_HOST = "dl.fbaipublicfiles.com"

#: DINOv2's positional-embedding interpolation as OTAS builds its ViT (the constructor
#: defaults of ``DinoVisionTransformer``): no antialiasing, scale factor offset 0.1.
_OTAS_INTERPOLATE_ANTIALIAS = False
_OTAS_INTERPOLATE_OFFSET = 0.1


def _hint() -> str:
    ckpt = OTAS_CHECKPOINTS[OTAS_ENTRY_POINT]
    return (
        f"Clone facebookresearch/dinov2 elsewhere and pass repo=/path/to/dinov2 "
        f"source=local; put {ckpt} (https://{_WEIGHTS_HOST}/dinov2/dinov2_vits14/{ckpt}) "
        f"in the torch hub cache ({os.path.join(torch.hub.get_dir(), 'checkpoints')})."
    )


def _positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{name}={value!r}: expected a positive integer")
    return value


class OtasEncoder(DenseEncoder, FrozenModule):
    """Frozen OTAS (DINOv2 ViT-S/14 reg4 clusters pooling CLIP ViT-B/16 value-path tokens).

    See the module docstring for what is computed. Defaults are OTAS's ``OTAS_small.json``
    (the configuration of its 2D inference helper).

    Args:
        repo: ``owner/name`` of DINOv2 on GitHub, or a local clone (``source="local"``).
        source: ``"github"`` or ``"local"``.
        entry_point: the DINOv2 hub entry point (``dinov2_vits14_reg``).
        clip: :class:`ClipEncoder` arguments (``model_name``, ``weights``, ``seed``) of the
            CLIP model; ``None`` = OpenAI ViT-B-16 (``{"weights": "openai"}``). Errors
            name ``clip.<key>``. (``image_size`` would build CLIP at another
            native size: OTAS uses the native 224, so only tiny tests set it.)
        dense_path: the CLIP tokens pooled per mask: ``"value"`` (OTAS's own, default) or
            ``"maskclip"`` (the official MaskCLIP's, residual and MLP kept); see step 3.
        dino_input_size: side of the square DINOv2 input (a multiple of 14).
        dino_scale_factor: bilinear upsampling of the DINOv2 token grid before clustering.
        shared_feat_resolution: side ``S`` of OTAS's square output grid.
        n_clusters: k-means clusters per image.
        n_components: PCA components per image.
        clip_input_size: CLIP's shorter input side (aspect kept).
        output_grid: ``"canvas"`` (the pooled map resized bilinearly to ``(H/14, W/14)``) or
            ``"shared"`` (the ``S x S`` map as OTAS computes it).
        device: where the models live (default CPU).
        ref: the git tag or commit SHA of DINOv2 loaded from GitHub (``"repo:ref"``;
            :func:`resireg.models.hub.hub_target`); conf/encoder/otas.yaml pins the one the
            adapter was checked against (:data:`resireg.models.hub.PINNED_REFS`, the default).
            ``None``: the default branch. Ignored for a local clone.
        **kwargs: passed to ``torch.hub.load`` (``trust_repo``, ``force_reload``, or the entry
            point's own arguments such as ``pretrained``).
    """

    def __init__(
        self,
        repo: str = "facebookresearch/dinov2",
        source: str = "github",
        entry_point: str = OTAS_ENTRY_POINT,
        clip: Mapping[str, Any] | None = None,
        dino_input_size: int = 224,
        dino_scale_factor: int = 1,
        shared_feat_resolution: int = 16,
        n_clusters: int = 24,
        n_components: int = 12,
        clip_input_size: int = 224,
        output_grid: str = "canvas",
        dense_path: str = "value",
        device: str | torch.device | None = None,
        ref: str | None = PINNED_REFS["facebookresearch/dinov2"],
        **kwargs: Any,
    ) -> None:
        super().__init__()
        if output_grid not in ("canvas", "shared"):
            raise ConfigError(f"output_grid={output_grid!r}: expected 'canvas' or 'shared'")
        self.dino_input_size = _positive_int(dino_input_size, "dino_input_size")
        self.dino_scale_factor = _positive_int(dino_scale_factor, "dino_scale_factor")
        self.shared_feat_resolution = _positive_int(
            shared_feat_resolution, "shared_feat_resolution"
        )
        self.n_clusters = _positive_int(n_clusters, "n_clusters")
        self.n_components = _positive_int(n_components, "n_components")
        self.clip_input_size = _positive_int(clip_input_size, "clip_input_size")
        self.output_grid = output_grid
        self.repo, self.source, self.entry_point, self.ref = repo, source, entry_point, ref
        self.hub_kwargs = dict(kwargs)  # torch.hub.load's / the entry point's (spec)

        # Fail at once, before torch.hub asks for anything it cannot reach.
        check_hub_source(repo, source, "DINOv2 for OTAS", _hint(), ref)
        target = hub_target(repo, source, ref)
        #: what torch.hub loads, ``"owner/name:ref"``, or ``None`` (a local clone, unpinned)
        self.hub_ref = target if target != repo else None
        ckpt = OTAS_CHECKPOINTS.get(entry_point)
        if ckpt is not None and kwargs.get("pretrained", True):
            require_hub_checkpoints([ckpt], "DINOv2 weights", _WEIGHTS_HOST, _hint())
        clip_args = {"weights": "openai", **dict(clip or {})}
        if "dense_path" in clip_args:
            raise ConfigError("clip.dense_path: pass dense_path= instead (OTAS's CLIP path)")
        check_dense_path(dense_path, "dense_path")  # before any model loads
        clip_model = clip_args.get("model_name", "ViT-B-16")
        clip_weights = clip_args["weights"]
        if clip_model in CLIP_MODELS and isinstance(clip_weights, str):
            if not os.path.isfile(clip_weights):  # the open_clip tag must be cached or reachable
                require_clip_weights(clip_model, clip_weights, "clip.weights")

        # A pinned commit is no branch or tag, which torch.hub's fork check looks for.
        pinned = {"skip_validation": True} if target != repo else {}
        dino = torch.hub.load(target, entry_point, source=source, **{**pinned, **kwargs})
        for attr in ("patch_size", "embed_dim", "forward_features"):
            if not hasattr(dino, attr):
                raise ConfigError(f"entry_point={entry_point!r}: not a DINOv2 ViT (no {attr!r})")
        # OTAS's own ViT copy interpolates the positional embedding with these settings.
        dino.interpolate_antialias = _OTAS_INTERPOLATE_ANTIALIAS
        dino.interpolate_offset = _OTAS_INTERPOLATE_OFFSET
        self.patch_size = int(dino.patch_size)
        self.dino_dim = int(dino.embed_dim)
        if self.dino_input_size % self.patch_size:
            raise ConfigError(
                f"dino_input_size={dino_input_size}: not a multiple of the patch size "
                f"{self.patch_size}"
            )
        tokens = (self.dino_input_size // self.patch_size * self.dino_scale_factor) ** 2
        if self.n_clusters > tokens:
            raise ConfigError(
                f"n_clusters={n_clusters}: more than the {tokens} DINOv2 tokens clustered"
            )
        if self.n_components > min(tokens, self.dino_dim):
            raise ConfigError(f"n_components={n_components}: at most {min(tokens, self.dino_dim)}")
        self.dino = dino
        clip_arguments = [a for a in parameters(ClipEncoder) if a != "dense_path"]  # (ours)
        with arguments_under("clip", clip_arguments):  # its errors name clip.<argument>
            self.clip = ClipEncoder(**clip_args, dense_path=dense_path)
        self.dense_path = self.clip.dense_path
        self.embed_dim = self.clip.embed_dim
        self._input_rule = InputRule(self.patch_size, IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD)
        self.to(torch.device(device if device is not None else "cpu"))
        self.freeze()

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside)."""
        return {
            "kind": "otas",
            "repo": self.repo,
            "source": self.source,
            "ref": self.ref,
            "entry_point": self.entry_point,
            "clip": {
                k: self.clip.spec()[k] for k in ("model_name", "weights", "seed", "image_size")
            },
            "dino_input_size": self.dino_input_size,
            "dino_scale_factor": self.dino_scale_factor,
            "shared_feat_resolution": self.shared_feat_resolution,
            "n_clusters": self.n_clusters,
            "n_components": self.n_components,
            "clip_input_size": self.clip_input_size,
            "output_grid": self.output_grid,
            "dense_path": self.dense_path,
            **self.hub_kwargs,
        }

    # ------------------------------------------------------------------ interface
    @property
    def input_rule(self) -> InputRule:
        return self._input_rule

    @torch.no_grad()
    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised canvas ``[B, 3, H, W]`` -> (DINOv2 tokens ``[B, 384, H/14, W/14]``,
        OTAS's pooled language features ``[B, 512, h, w]``, CLIP embedding ``[B, 512]``)."""
        self.input_rule.check_size(images)
        b, _, h, w = images.shape
        p = self.patch_size
        x = images.to(self.device, torch.float32)
        tokens = self.dino_tokens(x)
        clip_maps, embedding = self.clip_dense(x)
        pooled = torch.stack(
            [
                self.pool(self.cluster_map(t), self.shared_clip_map(c))
                for t, c in zip(tokens, clip_maps, strict=True)
            ]
        )
        g = self.dino_input_size // p
        grid = (h // p, w // p)
        language = pooled
        if self.output_grid == "canvas" and tuple(pooled.shape[-2:]) != grid:
            language = F.interpolate(pooled, size=grid, mode="bilinear", align_corners=False)
        return DenseOutput(tokens_to_grid(tokens, (g, g), grid), language, embedding)

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """CLIP's text embeddings ``[K, 512]`` (float32, not normalised)."""
        return self.clip.text_features(texts)

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Unit-norm text queries ``[K, 512]``, the language features' space."""
        return self.dense_text(self.text_features(texts))

    # ------------------------------------------------------------------ OTAS's steps
    def dino_tokens(self, x: Tensor) -> Tensor:
        """Step 1: ``x_norm_patchtokens`` ``[B, g*g, 384]`` of the canvas resized to the
        square DINOv2 input."""
        s = self.dino_input_size
        x = _resize(x, (s, s))
        return self.dino.forward_features(x)["x_norm_patchtokens"].float()

    def cluster_map(self, tokens: Tensor) -> Tensor:
        """Step 2: one image's patch tokens ``[g*g, D]`` -> k-means labels ``[S, S]`` (int64)."""
        try:
            from sklearn.cluster import KMeans
        except ImportError as err:  # pragma: no cover - scikit-learn is installed with dev
            raise ImportError(
                "OtasEncoder clusters with scikit-learn: pip install scikit-learn"
            ) from err
        g = math.isqrt(tokens.shape[0])
        if g * g != tokens.shape[0]:
            raise ValueError(f"{tokens.shape[0]} DINOv2 tokens do not form a square grid")
        grid = F.normalize(tokens.float(), dim=-1).T.reshape(1, -1, g, g)
        if self.dino_scale_factor != 1:
            grid = F.interpolate(
                grid, scale_factor=self.dino_scale_factor, mode="bilinear", align_corners=False
            )
        side = grid.shape[-1]
        flat = grid[0].flatten(1).T  # [side*side, D], row-major
        centred = flat - flat.mean(dim=0)
        _, _, vh = torch.linalg.svd(centred, full_matrices=False)
        reduced = F.normalize(centred @ vh[: self.n_components].T, dim=-1)
        kmeans = KMeans(
            n_clusters=self.n_clusters,
            init="k-means++",
            n_init=1,
            max_iter=300,
            tol=1e-4,
            random_state=0,
            algorithm="lloyd",
        )
        labels = torch.from_numpy(kmeans.fit_predict(reduced.cpu().numpy())).to(tokens.device)
        labels = labels.reshape(1, 1, side, side).float()
        s = self.shared_feat_resolution
        return F.interpolate(labels, size=(s, s), mode="nearest")[0, 0].long()

    def clip_dense(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Step 3: CLIP's dense tokens (``dense_path``) ``[B, 512, H'/16, W'/16]`` and the CLIP
        image embedding ``[B, 512]`` of the canvas with its shorter side resized to
        ``clip_input_size``."""
        h, w = x.shape[-2:]
        s = self.clip_input_size
        # torchvision's Resize(s): the shorter side to s, the longer one truncated.
        size = (s, int(s * w / h)) if w > h else (int(s * h / w), s)
        x = _resize(x, size)
        square = x.shape[-2] == x.shape[-1]
        visual = self.clip.model.visual
        feats = visual.conv1(x.to(visual.conv1.weight.dtype))  # [B, width, gh, gw]
        gh, gw = feats.shape[-2:]
        tokens = feats.flatten(2).transpose(1, 2)
        cls = visual.class_embedding.to(tokens.dtype).view(1, 1, -1).expand(tokens.shape[0], 1, -1)
        tokens = torch.cat([cls, tokens], dim=1)
        tokens = tokens + _clip_positions(visual.positional_embedding, gh, gw, square)
        tokens = visual.ln_pre(tokens)
        transformer = visual.transformer
        if not transformer.batch_first:
            tokens = tokens.transpose(0, 1)
        *blocks, last = transformer.resblocks
        for block in blocks:
            tokens = block(tokens)
        out = last(tokens)
        if not transformer.batch_first:
            tokens, out = tokens.transpose(0, 1), out.transpose(0, 1)
        values = ClipEncoder.dense_tokens(last, tokens, self.dense_path)[:, 1:]
        dense = visual.ln_post(values) @ visual.proj  # [B, gh*gw, 512]
        embedding = visual.ln_post(out[:, 0]) @ visual.proj
        maps = dense.float().transpose(1, 2).reshape(dense.shape[0], -1, gh, gw)
        return maps, embedding.float()

    def shared_clip_map(self, clip_map: Tensor) -> Tensor:
        """Step 4: one image's CLIP map ``[C, Hs, Ws]`` -> ``[C, S, S]`` by nearest lookup."""
        s = self.shared_feat_resolution
        hs, ws = clip_map.shape[-2:]
        steps = torch.arange(s, device=clip_map.device, dtype=torch.float32)
        rows = (steps * (hs / s)).floor().clamp(max=hs - 1).long()
        cols = (steps * (ws / s)).floor().clamp(max=ws - 1).long()
        return clip_map[:, rows][:, :, cols]

    @staticmethod
    def pool(labels: Tensor, features: Tensor) -> Tensor:
        """Step 5: labels ``[S, S]`` and features ``[C, S, S]`` -> every cell holds the
        L2-normalised mean feature of its label's cells ``[C, S, S]``."""
        c = features.shape[0]
        flat = features.reshape(c, -1).T.float()
        lab = labels.reshape(-1).to(flat.device)
        n = int(lab.max()) + 1
        sums = flat.new_zeros(n, c).index_add_(0, lab, flat)
        counts = torch.bincount(lab, minlength=n).clamp(min=1).to(flat.dtype)
        means = F.normalize(sums / counts[:, None], dim=-1)
        return means[lab].T.reshape(features.shape)


def _resize(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinear, antialiased (as PIL's resize in OTAS's transforms); a no-op at the same size."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


def _clip_positions(pos: Tensor, gh: int, gw: int, square: bool) -> Tensor:
    """CLIP's positional embedding ``[1 + n, D]`` for a ``gh x gw`` grid, as MaskCLIP-onnx
    interpolates it (bicubic, scale factor with a 0.1 offset, no antialiasing)."""
    n = pos.shape[0] - 1
    if gh * gw == n and square:
        return pos
    m = math.isqrt(n)
    patch = pos[1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
    patch = F.interpolate(
        patch,
        scale_factor=((gh + 0.1) / m, (gw + 0.1) / m),
        mode="bicubic",
        align_corners=False,
        recompute_scale_factor=False,
    )
    if tuple(patch.shape[-2:]) != (gh, gw):
        raise RuntimeError(
            f"positional embedding interpolated to {tuple(patch.shape[-2:])}, not {(gh, gw)}"
        )
    return torch.cat([pos[:1], patch.permute(0, 2, 3, 1).reshape(gh * gw, -1)], dim=0)
