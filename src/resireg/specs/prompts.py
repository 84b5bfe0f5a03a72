"""The prompt template sets of the class prototypes, by the name a 2D evaluation entry's
``templates`` key takes (``conf/protocol/paper.yaml``, ``ovss8.yaml``), without importing torch
or open_clip: each name and the open_clip constant that holds its templates
(:func:`resireg.ovss.template_set` resolves it).

- ``openai_imagenet``: the 80 templates of OpenAI's CLIP ImageNet evaluation, the paper's
  protocol and the OVSS field's;
- ``simple_imagenet``: open_clip's 7-template subset of them: 11x fewer text-tower passes per
  class, for quick looks and tests; its prototypes (and so the scores) differ from the
  protocol's, and the run's protocol record says which set it used.
"""

from __future__ import annotations

from resireg.specs.rules import Rule, one_of

__all__ = ["TEMPLATE_SET", "TEMPLATE_SETS"]

#: Template set name -> the open_clip constant holding its templates.
TEMPLATE_SETS: dict[str, str] = {
    "openai_imagenet": "OPENAI_IMAGENET_TEMPLATES",
    "simple_imagenet": "SIMPLE_IMAGENET_TEMPLATES",
}
#: The ``templates`` key's rule (the config check's and :func:`resireg.ovss.template_set`'s).
TEMPLATE_SET: Rule = one_of(tuple(TEMPLATE_SETS))
