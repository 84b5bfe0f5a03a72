"""Old import paths kept for one release: a module's ``__getattr__`` (PEP 562) that returns a
name from its new home with a ``DeprecationWarning`` naming it. Every moved module and renamed
class of the project uses this one function (``CHANGELOG.md``, "Deprecated")."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["moved"]


def moved(module: str, names: Mapping[str, str]) -> Callable[[str], Any]:
    """The ``__getattr__`` of ``module`` for names that left it: ``names`` maps an old name to
    ``"new.module"`` (same name there) or ``"new.module:NewName"``."""

    def __getattr__(name: str) -> Any:
        if name not in names:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        target, _, new_name = names[name].partition(":")
        new_name = new_name or name
        warnings.warn(f"{module}.{name} moved to {target}.{new_name}: import it from "
                      f"{target}; this alias goes in the next release", DeprecationWarning,
                      stacklevel=2)  # fmt: skip
        return getattr(importlib.import_module(target), new_name)

    return __getattr__
