"""Where a model comes from, decided without torch: the rule of
:meth:`resireg.models.ResiregVLM.from_pretrained` for its ``source`` (an export folder, a
Hugging Face repo id, or an export in MLflow's model registry, ``models:/NAME@ALIAS`` or
``models:/NAME/VERSION``: :mod:`resireg.models.vlm.registry`), shared with the config checks of
``resireg-eval`` and ``resireg-playground``, which run it before torch and the models load.
(This was ``resireg.sources`` before that name became the map's frame sources.)"""

from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

__all__ = ["REGISTRY_PREFIX", "export_source_problem", "is_repo_id", "registry_model"]

#: The scheme of an export in MLflow's model registry.
REGISTRY_PREFIX = "models:/"
_MODEL_URI = re.compile(r"^models:/(?P<name>[^/@]+)(?:@(?P<alias>[^/@]+)|/(?P<version>\d+))$")


def registry_model(text: str | os.PathLike) -> tuple[str, str | None, str | None] | None:
    """``(name, alias, version)`` of a model registry URI (``models:/NAME@ALIAS`` or
    ``models:/NAME/VERSION``, exactly one of alias and version set); ``None`` for anything
    that does not start with ``models:/``; a :class:`ValueError` naming the forms for one that
    does but has neither form."""
    text = os.fspath(text)
    if not text.startswith(REGISTRY_PREFIX):
        return None
    match = _MODEL_URI.match(text)
    if match is None:
        raise ValueError(f"{text!r} is not a model registry URI: expected models:/NAME@ALIAS "
                         "(e.g. models:/resireg-vlm@champion) or models:/NAME/VERSION")  # fmt: skip
    return match["name"], match["alias"], match["version"]


def is_repo_id(text: str) -> bool:
    """Whether ``text`` has the form of a Hugging Face repo id ``owner/name`` (one ``/``, not a
    path that starts at ``/``, ``.`` or ``~``)."""
    return text.count("/") == 1 and not text.startswith(("/", ".", "~"))


def export_source_problem(source: str | os.PathLike) -> str | None:
    """Why ``source`` cannot be a ``ResiregVLM`` export (``None`` when it may be one): an
    existing folder must hold ``config.json``; a ``models:/`` URI must have one of the
    registry's two forms and MLflow must be installed; anything else must be a repo id, looked
    up in the Hugging Face cache (then the hub) only when the model loads."""
    path, text = Path(source), os.fspath(source)
    try:
        if registry_model(text) is not None:
            if importlib.util.find_spec("mlflow") is None:
                return (f"{text!r} is in MLflow's model registry, and MLflow is not installed: "
                        "pip install 'resireg[tracking]'")  # fmt: skip
            return None  # looked up (and downloaded once) when the model loads
    except ValueError as err:
        return str(err)
    if path.is_dir():
        if (path / "config.json").is_file():
            return None
        return f"{text!r} holds no config.json (not a ResiregVLM export)"
    if path.exists() or not is_repo_id(text):
        return f"{text!r} is not an export folder (and not a Hugging Face repo id 'owner/name')"
    return None
