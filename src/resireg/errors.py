"""The project's error classes: one base, :class:`ResiregError`, and one class per kind of fault.

Every error the library raises on purpose derives from :class:`ResiregError`, so a caller (a
robot's node, a notebook, ``resireg_train``'s CLIs) can tell "resireg refused this input" from a
bug with one ``except``. Each kind also derives from the built-in class its callers already
catch (``ValueError`` for a bad value, ``RuntimeError`` for a state that cannot go on,
``OSError`` for a file that cannot be written), so existing ``except ValueError`` code keeps
working.

The library's messages name the library's own argument (``path='run.bag': no such folder``);
``resireg_train`` adds the config path at its boundary (``source.path='run.bag': ...``,
:func:`resireg_train.validation.config_path`), so no function of ``resireg`` takes a config
key to put in its messages.

Adding a kind: one class here, under the base it belongs to.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "DataError",
    "IntegrityError",
    "MapError",
    "OfflineError",
    "ResiregError",
]


class ResiregError(Exception):
    """The base of every error resireg raises on purpose."""


class ConfigError(ResiregError, ValueError):
    """A setting's value is not one the code accepts (the message names the setting and the
    value; at the CLIs, the config path)."""


class OfflineError(ResiregError, RuntimeError):
    """Weights or code that are not on this machine and cannot be downloaded (no network, or
    ``HF_HUB_OFFLINE``): the message names the setting that points at a local copy."""


class DataError(ResiregError, ValueError):
    """Input data that cannot be used: a damaged recording, a missing topic, non-finite
    features, a frame whose sizes disagree."""


class IntegrityError(DataError):
    """A saved file whose content is not what its digest says (damaged, truncated or edited)."""


class MapError(ResiregError, RuntimeError):
    """A map that cannot take what it was given (full, or built by another model)."""
