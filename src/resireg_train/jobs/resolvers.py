"""The OmegaConf resolvers ``conf/`` uses: the run folder's name (``safe_dirname``, ``run_id``),
rank 0's ``.hydra/`` (``if_rank_zero``), the search's metric and the encoder sweeps' table."""

from __future__ import annotations

import hashlib
import os

from omegaconf import OmegaConf

from resireg.secrets import MASK, mask_text
from resireg_train.config.machine import config_rank
from resireg_train.config.paths import RUN_ID

__all__ = ["register_resolvers", "safe_dirname"]


def safe_dirname(text: str, max_length: int = 200) -> str:
    """``text`` as one folder name: ``/`` becomes ``_``, a URL's password becomes ``masked``
    (a sweep job's folder is named after its overrides, a tracking URI's among them), and a
    name longer than ``max_length`` is cut and given a hash so it stays unique (Hydra's
    ``override_dirname`` keeps the ``/`` of paths given as values, which would nest folders)."""
    name = mask_text(str(text)).replace(MASK, "masked")
    name = name.replace("/", "_").replace(os.sep, "_")
    if len(name) > max_length:
        digest = hashlib.sha1(name.encode()).hexdigest()[:8]
        name = f"{name[: max_length - 9]}-{digest}"
    return name



def register_resolvers() -> None:
    """The OmegaConf resolvers ``conf/`` uses (``safe_dirname`` and ``run_id`` in ``conf/hydra``,
    ``if_rank_zero`` in ``conf/train.yaml``,
    ``first_key`` in ``conf/hparams_search``, ``resireg_encoders`` in the sweeps over every
    encoder)."""
    if not OmegaConf.has_resolver("safe_dirname"):
        OmegaConf.register_new_resolver("safe_dirname", safe_dirname)
    if not OmegaConf.has_resolver("run_id"):
        OmegaConf.register_new_resolver("run_id", lambda: RUN_ID, use_cache=True)
    if not OmegaConf.has_resolver("if_rank_zero"):
        # conf/train.yaml: .hydra/ is written by the global rank 0 alone (the nodes of a
        # multi-node run share its folder)
        OmegaConf.register_new_resolver(
            "if_rank_zero",
            lambda value, devices=None: value if config_rank({"trainer": {"devices": devices}})
            == 0 else None,
        )  # fmt: skip
    import resireg_train.checks.eval  # noqa: F401  registers resireg_encoders (conf/sweep/table*.yaml)
    from resireg_train.search.space import register_search_resolvers

    register_search_resolvers()  # conf/hparams_search/: the metric follows val_data=

