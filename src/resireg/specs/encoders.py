"""The dense encoders by ``kind``: one entry each, the only list of them.

Every reader takes the kinds from here: :func:`resireg.models.build_encoder` (the builder),
``resireg_train.validation`` (``encoder.kind`` and the modules each kind imports), the config
check of the sweeps over every encoder (``conf/sweep/table1.yaml``, ``table2.yaml``: their
``encoder`` axis must list :func:`encoder_configs`), the tests. An entry names the
``conf/encoder/<name>.yaml`` files of its kind: those hold the defaults of each configuration
(the builders' keyword defaults are the library's, for Python use).

An installed package adds kinds with an entry point in the group ``resireg.encoders`` naming an
:class:`EncoderSpec` (``toy = "my_pkg.spec:SPEC"``); they are looked up only for a kind the
built-in table lacks (:func:`find_encoder`), so the check of a built-in kind reads no package
metadata. Adding an encoder: one module (the :class:`~resireg.models.DenseEncoder`), one entry
here, one ``conf/encoder/`` file (docs/design.md section 13).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

__all__ = [
    "ENCODER_ENTRY_POINTS",
    "ENCODER_SPECS",
    "EncoderSpec",
    "Needs",
    "encoder_configs",
    "encoder_specs",
    "find_encoder",
]

#: The entry-point group of encoder kinds from other packages.
ENCODER_ENTRY_POINTS = "resireg.encoders"


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
            class or a function, called with the entry's keys, ``device`` and ``config_key``.
        configs: the ``conf/encoder/<name>.yaml`` files of this kind (their defaults).
        imports: modules beyond the core install its code imports (checked before a model
            loads, ``resireg_train.validation.encoder_import_errors``).
        needs_model_path: whether ``resireg-eval`` passes ``model_path`` as the entry's
            ``path`` (our VLM's export).
    """

    kind: str
    target: str
    configs: tuple[str, ...]
    imports: tuple[Needs, ...] = ()
    needs_model_path: bool = False

    def load(self) -> Callable[..., Any]:
        """The builder (imports torch and the encoder's code)."""
        from resireg.specs import load

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
#: ``kind -> spec``, in the order of docs/design.md section 6.
ENCODER_SPECS: dict[str, EncoderSpec] = {
    spec.kind: spec
    for spec in (
        EncoderSpec("resireg_vlm", "resireg.models.encoders:load_resireg_vlm", ("resireg_vlm",),
                    needs_model_path=True),
        EncoderSpec("clip", "resireg.models.zoo.clip:ClipEncoder",
                    ("clip_vit_b16", "clip_vit_l14_336")),
        EncoderSpec(
            "radio", "resireg.models.zoo.radio:RadioEncoder",
            ("radio_v3b_clip", "radio_v3b_siglip2", "radio_v4_siglip2"),
            (*_RADIO,
             Needs("transformers", "transformers", _SIGLIP, lambda e: e.get("adaptor") != "clip")),
        ),
        EncoderSpec(
            "radseg", "resireg.models.zoo.radio:RadSegEncoder", ("radseg",),
            (Needs("segment_anything", "segment-anything", "RADSeg hubconf.py, radseg/radseg.py"),
             Needs("skimage", "scikit-image", "RADSeg radseg/sam_utils.py"),
             Needs("typing_extensions", "typing-extensions", "RADSeg radseg/base.py, radseg.py"),
             *_RADIO,
             Needs("transformers", "transformers", f"{_SIGLIP}, which RADSeg loads")),
        ),
        EncoderSpec(
            "dinotxt", "resireg.models.zoo.dinotxt:DinoTxtEncoder", ("dinotxt",),
            (Needs("ftfy", "ftfy", _BPE),
             Needs("regex", "regex", _BPE),
             Needs("requests", "requests",
                   "facebookresearch/dinov2 dinov2/hub/dinotxt.py get_tokenizer (downloads the "
                   "vocabulary: vocab=null)", lambda e: e.get("vocab") is None)),
        ),
        EncoderSpec("tips", "resireg.models.zoo.tips:TipsEncoder", ("tipsv2",),
                    (Needs("sentencepiece", "sentencepiece",
                           "resireg.models.zoo.tips (its tokenizer)"),)),
        EncoderSpec("otas", "resireg.models.zoo.otas:OtasEncoder", ("otas",),
                    (Needs("sklearn", "scikit-learn", "resireg.models.zoo.otas (k-means)"),)),
    )
}  # fmt: skip


@functools.cache
def _plugins() -> dict[str, EncoderSpec]:
    """The kinds installed packages register (entry points of :data:`ENCODER_ENTRY_POINTS`)."""
    from importlib.metadata import entry_points

    found = {}
    for point in entry_points(group=ENCODER_ENTRY_POINTS):
        spec = point.load()
        if not isinstance(spec, EncoderSpec):
            raise TypeError(
                f"entry point {point.name} = {point.value!r} ({ENCODER_ENTRY_POINTS})"
                f": expected an EncoderSpec, got {type(spec).__name__}"
            )
        if spec.kind in ENCODER_SPECS:
            raise ValueError(
                f"entry point {point.value!r} ({ENCODER_ENTRY_POINTS}): kind "
                f"{spec.kind!r} is a built-in encoder kind"
            )
        found[spec.kind] = spec
    return found


def encoder_specs() -> dict[str, EncoderSpec]:
    """Every kind: the built-in table, then those of installed packages."""
    return {**ENCODER_SPECS, **_plugins()}


def find_encoder(kind: Any) -> EncoderSpec | None:
    """The spec of ``kind`` (built-in first; entry points only for another kind), or None."""
    if kind in ENCODER_SPECS:
        return ENCODER_SPECS[kind]
    return _plugins().get(kind) if isinstance(kind, str) else None


def encoder_configs() -> tuple[str, ...]:
    """Every built-in ``conf/encoder/`` configuration, by kind in table order: what a sweep
    over every encoder lists (Table 1, Table 2)."""
    return tuple(name for spec in ENCODER_SPECS.values() for name in spec.configs)
