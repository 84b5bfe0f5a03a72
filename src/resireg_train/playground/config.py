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
    from resireg_train.config.paths import CONFIG_DIR  # conf/ ($RESIREG_CONFIG_DIR overrides it)

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
    """``build_encoder`` keywords of an encoder config:
    :func:`resireg.specs.encoders.encoder_entry` on the project's ``conf/``."""
    from resireg.specs.encoders import encoder_entry

    return encoder_entry(encoder, model_path, config_dir or _config_dir())
