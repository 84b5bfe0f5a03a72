"""The playground's configuration, read without torch (so ``resireg-playground`` reports a bad
``--encoder`` or ``--model-path`` before the models and Gradio load): the encoder entry of
``conf/encoder/``, ReSiReg's defaults (``conf/resireg/default.yaml``) and the protocol's image
size (``conf/dataset/ade20k.yaml``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["SLIDERS", "encoder_spec", "reads_model_path", "resireg_defaults", "protocol_short_side"]

#: The ReSiReg parameters the page exposes as sliders (the rest of the YAML is kept).
SLIDERS: dict[str, tuple[str, ...]] = {
    "lite": ("alpha", "tau", "upscale"),
    "full": ("n_prototypes", "alpha", "tau", "upscale"),
}


def reads_model_path(spec: dict[str, Any]) -> bool:
    """Whether the encoder entry ``spec`` is our VLM's export (its kind's ``needs_model_path``
    in the encoder table, resireg.specs.encoders)."""
    from resireg.specs.encoders import ENCODER_SPECS

    found = ENCODER_SPECS.find(spec.get("kind"))
    return found is not None and found.needs_model_path


def _config_dir() -> Path:
    from resireg_train.paths import CONFIG_DIR  # conf/ ($RESIREG_CONFIG_DIR overrides it)

    return Path(CONFIG_DIR)


def _load_yaml(path: Path) -> Any:
    from omegaconf import OmegaConf

    return OmegaConf.load(path)


def resireg_defaults(config_dir: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """``{"lite": {...}, "full": {...}}``: ReSiReg's parameters from
    ``conf/resireg/default.yaml`` (the values ``resireg-eval`` and the training callback use)."""
    from omegaconf import OmegaConf

    path = Path(config_dir or _config_dir()) / "resireg" / "default.yaml"
    cfg = OmegaConf.to_container(_load_yaml(path), resolve=True)
    params = {name: dict(cfg[name]) for name in SLIDERS}
    n = params["full"]["n_prototypes"]
    if isinstance(n, bool) or not isinstance(n, int):
        raise ValueError(
            f"full.n_prototypes={n!r} in {path}: the playground's slider needs an integer"
        )
    return params


def protocol_short_side(config_dir: str | Path | None = None) -> int:
    """The evaluation protocol's shorter image side (``conf/dataset/ade20k.yaml``,
    ``short_side``): the playground's default input size."""
    path = Path(config_dir or _config_dir()) / "dataset" / "ade20k.yaml"
    return int(_load_yaml(path).short_side)


def encoder_spec(
    encoder: str | None = None,
    model_path: str | None = None,
    config_dir: str | Path | None = None,
) -> dict[str, Any]:
    """``build_encoder`` keywords (``kind`` and the entry's keys) of an encoder config.

    Args:
        encoder: a name of ``conf/encoder/`` (``clip_vit_b16``) or the path of such a YAML
            file; ``None`` means ``resireg_vlm`` (our VLM from ``model_path``).
        model_path: an export folder or hub repo id, for entries whose ``path`` is
            ``${model_path}``.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from resireg_train.validation import encoder_kwargs

    conf = Path(config_dir or _config_dir())
    name = encoder or "resireg_vlm"
    if name.endswith((".yaml", ".yml")) or "/" in name:
        path = Path(name).expanduser()
    else:
        path = conf / "encoder" / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (conf / "encoder").glob("*.yaml"))
        raise ValueError(f"--encoder={name!r}: no such config ({path}); expected one of {known} "
                         "or the path of an encoder YAML file")  # fmt: skip
    paths = _load_yaml(conf / "paths" / "default.yaml")
    root = OmegaConf.create({"model_path": model_path, "paths": paths})
    root.encoder = _load_yaml(path)
    try:
        spec = OmegaConf.to_container(root.encoder, resolve=True)
    except OmegaConfBaseException as err:
        raise ValueError(f"--encoder={name!r}: cannot resolve {path}: {err}") from err
    spec = encoder_kwargs(spec)
    if reads_model_path(spec) and not spec.get("path"):
        raise ValueError(
            f"--model-path is required with --encoder={name!r}: an export folder "
            "(resireg-train's <run>/export) or a Hugging Face repo id"
        )
    return spec
