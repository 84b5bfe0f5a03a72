"""Where a config meets the library: the config path added to the library's errors.

``resireg``'s messages name the function's own argument (``path='x': ...``); ``resireg_train``
names the config key to change (``source.path='x': ...``), here, at its boundary
(docs/architecture.md, "Errors"): :func:`config_path` around a library call,
:func:`block_errors` for the messages of a library check of a config block, :func:`key_errors`
around ``resireg_train``'s own checks of a config block whose messages name its keys.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from resireg.errors import (
    Arguments,
    ConfigError,
    add_note,
    argument_names,
    config_error_like,
    raised_by,
    rename_arguments,
    renamed,
)

__all__ = ["block_errors", "config_path", "encoder_arguments", "error_message", "key_errors"]


@contextmanager
def config_path(prefix: str, arguments: Arguments = ()) -> Iterator[None]:
    """The config path ``prefix`` added to the errors of the library calls inside: resireg's
    messages name the function's own argument (``path='x': ...``), the config names the entry.

    An error of resireg's code that names one of ``arguments`` (``name=...``, or a message that
    starts with the name: :func:`resireg.errors.rename_arguments`) names ``<prefix>.<name>``
    instead (``arguments`` may map a name to its whole config path: ``{"names": "variants"}``);
    one whose message starts with it comes back a :class:`ConfigError` (still of its own type:
    a ``FileNotFoundError`` stays one). Any other error gets the note ``config: <prefix>`` and
    goes on as it was. Errors of ``resireg_train``'s own code name their config paths already
    and pass untouched.

    Used where a config entry meets the library: ``encoder`` (``build_encoder``), ``prior``
    (``build_prior``), ``variants`` (``build_variants``), ``model.teacher`` (RADSeg)."""
    try:
        yield
    except Exception as err:
        if raised_by(err, "resireg_train"):
            raise
        new = renamed(err, argument_names(prefix, arguments))
        if new is not None:
            raise new from err
        add_note(err, f"config: {prefix}")
        raise


@contextmanager
def key_errors(key: str) -> Iterator[None]:
    """The errors raised inside whose message starts with the config block ``key``
    (``dataset.path='x': no folder ...``, ``dataset.split='val': ... lists no image``,
    ``dataset: the dataset is empty``) come back :class:`ConfigError` s, still of their own type
    (a ``FileNotFoundError`` stays one): their message names the setting to change, so the
    commands report them in one line, as a bad value. Other errors pass untouched.

    Used around the checks and builds of a dataset entry (``resireg_train.data``), whose
    messages name ``<key>.<field>`` as the project's messages do."""
    try:
        yield
    except (OSError, ValueError) as err:
        message = str(err)
        if isinstance(err, ConfigError) or not message.startswith((f"{key}.", f"{key}:")):
            raise
        try:
            new = config_error_like(type(err))(message)
        except Exception:  # a constructor that takes other arguments
            new = ConfigError(message)
        for note in getattr(err, "__notes__", ()):
            add_note(new, note)
        raise new from err


def block_errors(messages: Iterable[str], key: str, names: Iterable[str]) -> list[str]:
    """The messages of a library check of the config block at ``key`` (a source block's
    :func:`resireg.specs.sources.source_errors`), as a config error names them: each of the
    block's keys ``names`` a message names written ``<key>.<name>`` (``kind='x'`` ->
    ``source.kind='x'``), and ``<key>: `` before a message about the block as a whole."""
    renames = argument_names(key, tuple(names))
    out = []
    for message in messages:
        text, starts = rename_arguments(message, renames)
        out.append(text if starts else f"{key}: {text}")
    return out


def encoder_arguments(entry: Any) -> tuple[str, ...]:
    """What the messages of ``build_encoder(**entry)`` may name: the entry's keys and
    :func:`resireg.models.factory.encoder_arguments` (``kind``, ``device``, the builder's
    arguments; the builder is imported, as ``build_encoder`` would, and one that does not
    import leaves them out: ``build_encoder`` reports that)."""
    from resireg.models.factory import encoder_arguments as of_kind

    keys = tuple(entry) if isinstance(entry, dict) else ()
    try:
        named = of_kind(entry.get("kind")) if isinstance(entry, dict) else ()
    except Exception:
        named = ("kind", "device")
    return tuple(dict.fromkeys((*keys, *named)))


def error_message(err: BaseException) -> str:
    """``str(err)`` and its notes (``config: encoder``), one per line."""
    return "\n".join([str(err), *map(str, getattr(err, "__notes__", None) or ())])
