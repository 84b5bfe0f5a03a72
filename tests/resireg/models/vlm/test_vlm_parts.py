"""ResiregVLM refuses parts whose sizes do not fit together (issue 22, case 15)."""

import pytest
import torch

from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.models import ResiregVLM
from resireg.models.vlm.eupe import EUPEBackbone
from resireg.models.vlm.head import LanguageHead
from resireg.models.vlm.text import FrozenTextTower, TextProjection


@pytest.fixture(scope="module")
def parts():
    torch.manual_seed(0)
    return EUPEBackbone(**TINY_BACKBONE), FrozenTextTower.from_spec(TINY_TEXT)


def test_parts_of_disagreeing_sizes_are_refused_naming_both_sizes(parts):
    backbone, text = parts
    head48 = LanguageHead(in_dim=backbone.embed_dim, **{**TINY_HEAD, "out_dim": 48})
    # The case: 48-d image features against a projection whose dense half is 96-d.
    with pytest.raises(ValueError, match=r"the text projection's dense half is 96-d \(192 "
                       r"outputs\) but the head's patch tokens are 48-d"):  # fmt: skip
        ResiregVLM(backbone, head48, text, TextProjection(text.out_dim, 96))
    with pytest.raises(ValueError, match=rf"the text projection takes 32-d inputs but the text "
                       rf"tower gives {text.out_dim}-d"):  # fmt: skip
        ResiregVLM(backbone, head48, text, TextProjection(32, 48))
    wide = LanguageHead(in_dim=2 * backbone.embed_dim, **TINY_HEAD)
    with pytest.raises(ValueError, match=rf"the head takes {2 * backbone.embed_dim}-d tokens but "
                       rf"the backbone gives {backbone.embed_dim}-d"):  # fmt: skip
        ResiregVLM(backbone, wide, text, TextProjection(text.out_dim, wide.out_dim))


def test_fitting_parts_build_and_score_images_against_texts_of_one_width(parts):
    backbone, text = parts
    head = LanguageHead(in_dim=backbone.embed_dim, **{**TINY_HEAD, "out_dim": 48})
    vlm = ResiregVLM(backbone, head, text, TextProjection(text.out_dim, 48)).eval()
    dense = vlm.encode_image(torch.rand(3, 64, 80), resireg="bb")
    queries = vlm.encode_text(["a car", "road"])
    assert dense.shape[1] == queries.shape[1] == 48
