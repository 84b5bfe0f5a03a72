"""The dense encoders by ``kind``: one entry each, the only list of them.

Every reader takes the kinds from here: :func:`resireg.models.build_encoder` (the builder),
``resireg_train.checks.eval`` (``encoder.kind`` and the modules each kind imports), the config
check of the sweeps over every encoder (``conf/sweep/table1.yaml``, ``table2.yaml``: their
``encoder`` axis is generated from the table: ``${resireg_encoders:}``), the tests. The
``conf/encoder/<name>.yaml`` files of a kind are found by scanning ``conf/encoder/`` for their
``kind`` (:meth:`~resireg.specs.table.SpecTable.configs`); they hold the defaults of each
configuration (the builders' keyword defaults are the library's, for Python use).

An installed package adds kinds with an entry point in the group ``resireg.encoders`` naming an
:class:`EncoderSpec` (``toy = "my_pkg.spec:SPEC"``); they are looked up only for a kind the
built-in table lacks (:meth:`~resireg.specs.table.SpecTable.find`), so the check of a built-in
kind reads no package metadata.

Adding an encoder: one module with the :class:`~resireg.models.DenseEncoder` subclass (or a
builder function), one :class:`EncoderSpec` below (its builder and the modules it imports beyond
the core install, which the ``encoders`` extra in ``pyproject.toml`` installs), one
``conf/encoder/<name>.yaml`` file with its ``kind``. The Table 1 / Table 2 sweeps, the config
checks and ``tests/resireg/specs/test_tables.py`` pick it up from here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

from resireg.specs.table import SpecTable

__all__ = [
    "ENCODER_ENTRY_POINTS",
    "ENCODER_REPORT_KEYS",
    "ENCODER_SPECS",
    "EncoderSpec",
    "Needs",
    "encoder_entry",
    "encoder_kwargs",
]

#: The entry-point group of encoder kinds from other packages.
ENCODER_ENTRY_POINTS = "resireg.encoders"
#: Keys of a ``conf/encoder/`` entry that describe it in reports; the others are the keywords
#: of ``resireg.models.build_encoder``.
ENCODER_REPORT_KEYS = ("name", "third_party")


class Needs(NamedTuple):
    """A module an encoder's code imports: the pip distribution that provides it, who imports
    it, and when (``None``: always; else a test of the encoder entry)."""

    module: str
    dist: str
    who: str
    when: Callable[[dict], bool] | None = None


@dataclass(frozen=True)
class EncoderSpec:
    """One encoder kind.

    Attributes:
        kind: ``encoder.kind`` of its config entries.
        target: its builder, ``"module:attribute"``: a :class:`~resireg.models.DenseEncoder`
            class or a function, called with the entry's keys and ``device``.
        imports: modules beyond the core install its code imports (checked before a model
            loads, ``resireg_train.config.machine.encoder_import_errors``).
        needs_model_path: whether ``resireg-eval`` passes ``model_path`` as the entry's
            ``path`` (our VLM's export).
    """

    kind: str
    target: str
    imports: tuple[Needs, ...] = ()
    needs_model_path: bool = False

    @property
    def configs(self) -> tuple[str, ...]:
        """The ``conf/encoder/<name>.yaml`` files of this kind (their ``kind`` is this one)."""
        return ENCODER_SPECS.configs(self.kind)

    def load(self) -> Callable[..., Any]:
        """The builder (imports torch and the encoder's code)."""
        from resireg.specs.table import load

        return load(self.target)


_SIGLIP = "NVlabs/RADIO radio/siglip2_adaptor.py (its SigLIP 2 adaptors)"
_RADIO = (
    Needs("einops", "einops", "NVlabs/RADIO hubconf.py (dependencies) and radio/*.py"),
    Needs(
        "distutils",
        "setuptools",
        "NVlabs/RADIO radio/extra_models.py (Python >= 3.12: setuptools provides distutils)",
    ),
)
_BPE = "facebookresearch/dinov2 dinov2/thirdparty/CLIP (the dino.txt BPE tokenizer)"

# What an encoder kind imports beyond the core install: its own code in ``resireg.models`` and
# the upstream hub code it loads, read in those repositories (NVlabs/RADIO ``hubconf.py`` and
# ``radio/``; RADSeg-OVSS/RADSeg ``hubconf.py`` and ``radseg/``, which loads NVlabs/RADIO;
# facebookresearch/dinov2 ``hubconf.py`` and ``dinov2/``). The ``encoders`` extra installs them
# all (pyproject.toml lists them beside each encoder). ``clip`` and ``resireg_vlm`` need only
# the core.
#: ``kind -> spec``, in the order of docs/models.md#models-and-encoders.
ENCODER_SPECS: SpecTable[EncoderSpec] = SpecTable(
    "encoder kind",
    (
        EncoderSpec("resireg_vlm", "resireg.models.factory:load_resireg_vlm",
                    needs_model_path=True),
        EncoderSpec("clip", "resireg.models.zoo.clip:ClipEncoder"),
        EncoderSpec(
            "radio", "resireg.models.zoo.radio:RadioEncoder",
            (*_RADIO,
             Needs("transformers", "transformers", _SIGLIP, lambda e: e.get("adaptor") != "clip")),
        ),
        EncoderSpec(
            "radseg", "resireg.models.zoo.radseg:RadSegEncoder",
            (Needs("segment_anything", "segment-anything", "RADSeg hubconf.py, radseg/radseg.py"),
             Needs("skimage", "scikit-image", "RADSeg radseg/sam_utils.py"),
             Needs("typing_extensions", "typing-extensions", "RADSeg radseg/base.py, radseg.py"),
             *_RADIO,
             Needs("transformers", "transformers", f"{_SIGLIP}, which RADSeg loads")),
        ),
        EncoderSpec(
            "dinotxt", "resireg.models.zoo.dinotxt:DinoTxtEncoder",
            (Needs("ftfy", "ftfy", _BPE),
             Needs("regex", "regex", _BPE),
             Needs("requests", "requests",
                   "facebookresearch/dinov2 dinov2/hub/dinotxt.py get_tokenizer (downloads the "
                   "vocabulary: vocab=null)", lambda e: e.get("vocab") is None)),
        ),
        EncoderSpec("tips", "resireg.models.zoo.tips:TipsEncoder",
                    (Needs("sentencepiece", "sentencepiece",
                           "resireg.models.zoo.tips (its tokenizer)"),)),
        EncoderSpec("otas", "resireg.models.zoo.otas:OtasEncoder",
                    (Needs("sklearn", "scikit-learn", "resireg.models.zoo.otas (k-means)"),)),
    ),
    name="kind",
    where="resireg.specs.encoders",
    conf="encoder",
    entry_points=ENCODER_ENTRY_POINTS,
)  # fmt: skip


def encoder_kwargs(entry: Any) -> dict[str, Any]:
    """``build_encoder``'s keywords (``kind`` and the builder's keys) of an encoder entry."""
    return {k: v for k, v in entry.items() if k not in ENCODER_REPORT_KEYS}


def encoder_entry(
    encoder: str | None = None, model_path: str | None = None, config_dir: Any = None
) -> dict[str, Any]:
    """``build_encoder`` keywords (``kind`` and the entry's keys) of a ``conf/encoder/`` file,
    its interpolations (``${model_path}``, ``${paths.data_dir}``) resolved with OmegaConf (the
    ``train`` extra installs it; ``resireg-segment --encoder`` and the playground read entries
    this way, outside Hydra).

    Args:
        encoder: a name of ``conf/encoder/`` (``clip_vit_b16``) or the path of such a YAML
            file; ``None`` means ``resireg_vlm`` (our VLM from ``model_path``).
        model_path: an export folder or hub repo id, for entries whose ``path`` is
            ``${model_path}``.
        config_dir: the ``conf/`` folder (default: :func:`resireg.specs.table.conf_dir`).
    """
    from pathlib import Path

    from resireg.specs.table import conf_dir

    try:
        from omegaconf import OmegaConf
        from omegaconf.errors import OmegaConfBaseException
    except ImportError as err:
        raise ImportError(f"reading conf/encoder/ needs OmegaConf ({err}): "
                          "pip install 'resireg[train]'") from err  # fmt: skip
    conf = Path(config_dir or conf_dir())
    name = encoder or "resireg_vlm"
    if name.endswith((".yaml", ".yml")) or "/" in name:
        path = Path(name).expanduser()
    else:
        path = conf / "encoder" / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (conf / "encoder").glob("*.yaml"))
        raise ValueError(f"--encoder={name!r}: no such config ({path}); expected one of {known} "
                         "or the path of an encoder YAML file")  # fmt: skip
    paths = OmegaConf.load(conf / "paths" / "default.yaml")
    root = OmegaConf.create({"model_path": model_path, "paths": paths})
    root.encoder = OmegaConf.load(path)
    try:
        spec = OmegaConf.to_container(root.encoder, resolve=True)
    except OmegaConfBaseException as err:
        raise ValueError(f"--encoder={name!r}: cannot resolve {path}: {err}") from err
    spec = encoder_kwargs(spec)
    found = ENCODER_SPECS.find(spec.get("kind"))
    if found is not None and found.needs_model_path and not spec.get("path"):
        raise ValueError(
            f"--model-path is required with --encoder={name!r}: an export folder "
            "(resireg-train's <run>/export) or a Hugging Face repo id"
        )
    return spec
