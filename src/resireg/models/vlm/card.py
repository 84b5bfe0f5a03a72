"""The folder :meth:`ResiregVLM.push_to_hub` uploads: the export, verified, with a Hugging Face
model card (``README.md``: YAML front matter that ``huggingface_hub.ModelCard`` parses, and a
body that says what the model is, how to load it and which digests its files have) and a
``SHA256SUMS`` file (``sha256sum -c SHA256SUMS`` checks a download without Python)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from resireg.integrity import atomic_write, digests, resolve_inside
from resireg.models.vlm.folder import read_config

__all__ = ["CARD_DEFAULTS", "hub_folder", "model_card"]

#: The card's metadata unless the caller's ``card`` fields replace them.
CARD_DEFAULTS: dict[str, Any] = {
    "library_name": "resireg",
    "license": "apache-2.0",
    "pipeline_tag": "image-segmentation",
    "tags": [
        "resireg",
        "open-vocabulary-segmentation",
        "dense-vision-language",
        "vision-language",
        "pytorch",
        "safetensors",
    ],
}


def _describe(cfg: dict[str, Any]) -> str:
    backbone, head, text = cfg["backbone"], cfg["head"], cfg["text"]
    dims = ", ".join(
        f"{k}={backbone[k]}" for k in ("embed_dim", "depth", "num_heads") if k in backbone
    )
    tower = text.get("model_name", f"tiny ({text.get('layers')} layers, {text.get('width')} wide)")
    return (
        f"- backbone (frozen): timm `{backbone['model_name']}`{f' ({dims})' if dims else ''}, "
        f"weights: {backbone['weights'] or 'embedded in frozen.safetensors'}\n"
        f"- language head (trained): {head['depth']} blocks, {head['num_heads']} heads, "
        f"{head['out_dim']}-d dense tokens\n"
        f"- text tower (frozen): {tower}, weights: "
        f"{text.get('weights') or 'embedded in frozen.safetensors'}; trained projection\n"
        f"- ReSiReg intermediates: "
        f"{'final-norm patch tokens' if cfg.get('intermediate_layer') is None else 'block ' + str(cfg['intermediate_layer'])}"
    )


def model_card(cfg: dict[str, Any], repo_id: str, files: dict[str, str], card: dict | None = None):
    """A ``huggingface_hub.ModelCard`` for the export whose ``config.json`` is ``cfg``, to be
    published as ``repo_id``; ``files`` are the ``{name: sha256}`` listed in it; ``card``'s
    fields are added to (or replace) :data:`CARD_DEFAULTS` in the front matter."""
    from huggingface_hub import ModelCard, ModelCardData

    data = ModelCardData(**{**CARD_DEFAULTS, **(card or {})})
    sums = "\n".join(f"| `{name}` | `{digest}` |" for name, digest in sorted(files.items()))
    body = f"""
# {repo_id.split("/")[-1]}

A dense vision-language model of the ReSiReg project: images give language-aligned dense
features (`[B, {cfg["head"]["out_dim"]}, H/16, W/16]`) and text gives queries in the same
space, for open-vocabulary semantic segmentation; ReSiReg Lite and Full reconstruct
spatially consistent features from the backbone's intermediates.

{_describe(cfg)}

## Use

```python
from resireg.models import ResiregVLM

model = ResiregVLM.from_pretrained("{repo_id}")          # verifies the files' SHA-256
features = model.encode_image(images, "lite")            # [B, {cfg["head"]["out_dim"]}, h, w], unit norm
queries = model.encode_text(["floor", "chair", "table"])  # [3, {cfg["head"]["out_dim"]}]
```

One image, from the command line:

```bash
resireg-segment photo.jpg --labels "floor,chair,table" --model-path {repo_id} --variant lite --out seg.png
```

or through `torch.hub` (the ResiReg repository's `hubconf.py`):
`torch.hub.load("<owner>/resireg", "resireg_vlm", path_or_repo="{repo_id}")`.

## Files

`config.json` names every part and records the SHA-256 of each tensor file (`digests`);
`from_pretrained` checks them before any weight is read. `SHA256SUMS` lists every file
(`sha256sum -c SHA256SUMS`).

| file | SHA-256 |
| --- | --- |
{sums}
"""
    return ModelCard(f"---\n{data.to_yaml()}\n---\n{body}")


#: What a published card keeps of the export's own card (its front matter).
_CARRIED = ("model_name", "datasets", "eval_results", "base_model")


def _card_of(export: Path) -> tuple[dict[str, Any], str] | None:
    """``(front-matter fields, provenance and evaluation sections)`` of the export's own
    ``README.md`` (written by ``resireg-train``, extended by ``resireg-runs card``), if any."""
    from huggingface_hub import ModelCard

    path = export / "README.md"
    if not path.is_file():
        return None
    card = ModelCard.load(path)
    fields = {k: getattr(card.data, k) for k in _CARRIED if getattr(card.data, k, None)}
    at = card.text.find("\n## Provenance")
    return fields, (card.text[at:] if at >= 0 else "")


def hub_folder(
    export: str | os.PathLike,
    dest: str | os.PathLike,
    repo_id: str,
    card: dict[str, Any] | None = None,
) -> Path:
    """Lay out in ``dest`` what :meth:`ResiregVLM.push_to_hub` uploads: the export's
    ``config.json`` and the tensor files it records, verified first (a damaged export is not
    published: :class:`~resireg.integrity.IntegrityError`); ``README.md`` (:func:`model_card`)
    and ``SHA256SUMS``. Returns ``dest``."""
    export, dest = Path(export), Path(dest)
    cfg = read_config(export)  # verified; its file names stay inside the export
    names = ["config.json", *sorted(cfg.get("digests") or {})]
    if not cfg.get("digests"):  # an export from before digests: its tensor files by name
        names += [n for n in ("model.safetensors", cfg.get("frozen_weights")) if n]
    dest.mkdir(parents=True, exist_ok=True)
    for name in dict.fromkeys(names):
        where = f"{export}/config.json: file"
        shutil.copyfile(resolve_inside(export, name, where), resolve_inside(dest, name, where))
    sums = digests(dest, dict.fromkeys(names))
    made = _card_of(export)  # the card resireg-train wrote (results, data, provenance)
    fields = {**({k: v for k, v in made[0].items() if k in _CARRIED} if made else {}),
              **(card or {})}  # fmt: skip
    text = str(model_card(cfg, repo_id, sums, fields))
    if made and made[1]:
        text += made[1]
    atomic_write(dest / "README.md", lambda tmp: tmp.write_text(text))
    lines = "".join(f"{digest}  {name}\n" for name, digest in sums.items())
    atomic_write(dest / "SHA256SUMS", lambda tmp: tmp.write_text(lines))
    return dest
