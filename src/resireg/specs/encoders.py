"""The dense encoders by ``kind``: one entry each, the only list of them.

Every reader takes the kinds from here: :func:`resireg.models.build_encoder` (the builder),
``resireg_train.validation`` (``encoder.kind`` and the modules each kind imports), the config
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
checks and ``tests/test_tables.py`` pick it up from here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

from resireg.specs.table import SpecTable

__all__ = [
    "ENCODER_ENTRY_POINTS",
    "ENCODER_SPECS",
    "EncoderSpec",
    "Needs",
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
            class or a function, called with the entry's keys and ``device``.
        imports: modules beyond the core install its code imports (checked before a model
            loads, ``resireg_train.validation.encoder_import_errors``).
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
#: ``kind -> spec``, in the order of docs/design.md section 6.
ENCODER_SPECS: SpecTable[EncoderSpec] = SpecTable(
    "encoder kind",
    (
        EncoderSpec("resireg_vlm", "resireg.models.encoders:load_resireg_vlm",
                    needs_model_path=True),
        EncoderSpec("clip", "resireg.models.zoo.clip:ClipEncoder"),
        EncoderSpec(
            "radio", "resireg.models.zoo.radio:RadioEncoder",
            (*_RADIO,
             Needs("transformers", "transformers", _SIGLIP, lambda e: e.get("adaptor") != "clip")),
        ),
        EncoderSpec(
            "radseg", "resireg.models.zoo.radio:RadSegEncoder",
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
