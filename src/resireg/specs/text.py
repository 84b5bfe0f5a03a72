"""The frozen text towers of the 25M VLM by ``kind`` (``conf/model/text/<name>.yaml``,
``model.text``): one entry each, the only list of them, without importing torch.

:meth:`resireg.models.vlm.text.FrozenTextTower.from_spec` builds a tower from its config (or
from an export's ``config.json``) by looking its ``kind`` up here and calling the entry's
builder with the other keys; the config check (``resireg_train.checks.train``) reads the kinds
and :data:`CACHE_SIZE` before torch loads.

Adding a text tower:

1. a builder returning a :class:`resireg.models.vlm.text.FrozenTextTower` (a classmethod of it,
   as :meth:`~resireg.models.vlm.text.FrozenTextTower.tiny`, or a function in its own
   module): an open_clip-style text transformer, its tokenizer, its pooled width and the
   ``spec`` (``kind`` and the keywords) that rebuilds it, taking ``cache_size``;
2. one :class:`TextSpec` below: its ``kind``, the builder as ``"module:attribute"``
   (``"resireg.models.vlm.text:FrozenTextTower.tiny"``), a one-line summary;
3. one ``conf/model/text/<name>.yaml``: ``kind: <kind>``, the builder's keywords and
   ``cache_size``. ``model/text=<name>`` then selects it.

``tests/resireg/specs/test_tables.py`` checks the entry (its builder loads, its file is found by scanning).
"""

from __future__ import annotations

from resireg.specs.rules import Rule, optional_int
from resireg.specs.table import KindSpec, SpecTable

__all__ = ["CACHE_SIZE", "TEXT_SPECS", "TextSpec"]

#: ``cache_size`` of every tower (``conf/model/text/*.yaml``): captions whose outputs are kept.
CACHE_SIZE: Rule = optional_int(0)


class TextSpec(KindSpec):
    """One kind of text tower: its builder (``"module:attribute"``) and what it is."""


#: Text tower kinds of :meth:`resireg.models.vlm.text.FrozenTextTower.from_spec`.
TEXT_SPECS: SpecTable[TextSpec] = SpecTable(
    "text tower kind",
    (
        TextSpec("pretrained", "resireg.models.vlm.text:FrozenTextTower.pretrained",
                 "an open_clip model's text transformer with its weights (SigLIP 2, webli)"),
        TextSpec("tiny", "resireg.models.vlm.text:FrozenTextTower.tiny",
                 "a random 2-layer open_clip text transformer, CLIP's bundled BPE (offline)"),
    ),
    name="kind",
    where="resireg.specs.text",
    conf="model/text",
)  # fmt: skip
