"""The project's error classes: one base, :class:`ResiregError`, and one class per kind of fault.

Every error the library raises on purpose derives from :class:`ResiregError`, so a caller (a
robot's node, a notebook, ``resireg_train``'s CLIs) can tell "resireg refused this input" from a
bug with one ``except``. Each kind also derives from the built-in class its callers already
catch (``ValueError`` for a bad value, ``RuntimeError`` for a state that cannot go on,
``OSError`` for a file that cannot be written), so existing ``except ValueError`` code keeps
working.

The library's messages name the library's own argument (``path='run.bag': no such folder``);
``resireg_train`` adds the config path at its boundary (``source.path='run.bag': ...``,
:func:`resireg_train.config.errors.config_path`), so no function of ``resireg`` takes a config
key to put in its messages.

Adding a kind: one class here, under the base it belongs to.

**Naming arguments.** A message names an argument as ``name=value`` (anywhere), or starts with
the argument's name (``path is required``, ``tokenizer: expected a path``). A caller that passed
the argument from somewhere else renames it with :func:`renamed` (or :func:`arguments_under`):
:class:`~resireg.models.zoo.otas.OtasEncoder` turns its CLIP's ``weights=`` into
``clip.weights=``, ``resireg_train`` turns a builder's ``path=`` into ``encoder.path=``.
"""

from __future__ import annotations

import functools
import inspect
import re
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager

__all__ = [
    "ConfigError",
    "DataError",
    "IntegrityError",
    "MapError",
    "OfflineError",
    "ResiregError",
    "add_note",
    "argument_names",
    "arguments_under",
    "config_error_like",
    "parameters",
    "raised_by",
    "rename_arguments",
    "renamed",
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


class WriteError(ResiregError, OSError):
    """A file could not be written (disk full, quota, permissions); one line naming it and what
    it was (:func:`resireg.integrity.atomic_write`)."""


# -- naming arguments -------------------------------------------------------------------------

#: What a caller renames: argument names (each becomes ``<prefix>.<argument>``), or
#: ``{argument: new name}``.
Arguments = Iterable[str] | Mapping[str, str]


def argument_names(prefix: str, arguments: Arguments) -> dict[str, str]:
    """``{argument: new name}``: a mapping as given, else each argument as
    ``<prefix>.<argument>``."""
    if isinstance(arguments, Mapping):
        return {str(k): str(v) for k, v in arguments.items()}
    return {a: f"{prefix}.{a}" for a in arguments}


def parameters(function: Callable[..., object]) -> tuple[str, ...]:
    """The names of ``function``'s parameters (a class: its constructor's), ``*args`` and
    ``**kwargs`` left out: the arguments its messages may name."""
    kinds = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    try:
        signature = inspect.signature(function)
    except (TypeError, ValueError):  # a builtin without a signature
        return ()
    return tuple(n for n, p in signature.parameters.items() if p.kind not in kinds)


@functools.lru_cache(maxsize=256)
def _pattern(names: tuple[str, ...]) -> re.Pattern[str]:
    alternatives = "|".join(re.escape(n) for n in sorted(names, key=len, reverse=True))
    return re.compile(
        # at the start: the argument (or a key of it) followed by '=', ':' or a space
        rf"^(?P<lead>{alternatives})(?P<lead_keys>(?:\.\w+)*)(?=[=:\s])"
        # anywhere: ``name=`` (``name.key=``) not inside a word, a dotted name, a quoted
        # string or a path
        rf"|(?<![\w.'\"/\\-])(?P<name>{alternatives})(?P<keys>(?:\.\w+)*)(?==(?!=))"
    )


def rename_arguments(message: str, names: Mapping[str, str]) -> tuple[str, bool]:
    """``message`` with every argument of ``names`` it names (module docstring) renamed
    ``names[argument]``, and whether the message starts with one (it is about that argument's
    value)."""
    if not names:
        return message, False
    starts = False

    def rename(match: re.Match[str]) -> str:
        nonlocal starts
        if match.start() == 0:
            starts = True
        name = match.group("lead") or match.group("name")
        keys = match.group("lead_keys") or match.group("keys") or ""
        return names[name] + keys

    return _pattern(tuple(names)).sub(rename, message), starts


def raised_by(err: BaseException, package: str) -> bool:
    """Whether ``err`` was raised by the code of ``package`` (its innermost frame's module)."""
    tb = err.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    module = str(tb.tb_frame.f_globals.get("__name__", ""))
    return module == package or module.startswith(f"{package}.")


@functools.cache
def config_error_like(cls: type[BaseException]) -> type[BaseException]:
    """A :class:`ConfigError` that is also a ``cls`` (so ``except cls`` still catches it), shown
    and pickled as ``cls``; ``cls`` itself if it is one, :class:`ConfigError` for a plain
    ``ValueError`` or a class that cannot be combined with it."""
    if issubclass(cls, ConfigError):
        return cls
    if cls is ValueError:
        return ConfigError
    try:
        return type(
            cls.__name__,
            (ConfigError, cls),
            {
                "__module__": cls.__module__,
                "__qualname__": cls.__qualname__,
                "__doc__": cls.__doc__,
                "__reduce__": lambda self: (cls, self.args),
            },
        )
    except TypeError:  # an instance layout ConfigError cannot share
        return ConfigError


def renamed(err: BaseException, names: Mapping[str, str]) -> BaseException | None:
    """A new error whose message names each argument of ``names`` by its new name, or ``None``
    when ``err`` names none of them, was not raised by resireg's code (whose messages follow
    the rule of the module docstring) or has no plain message.

    An error whose message starts with an argument is about that argument's value: it comes back
    a :class:`ConfigError` that is still a ``type(err)`` (a ``FileNotFoundError`` stays one);
    another (an offline error whose hint names the argument) keeps its type."""
    if not raised_by(err, "resireg"):
        return None
    if len(err.args) != 1 or not isinstance(err.args[0], str) or str(err) != err.args[0]:
        return None
    message, starts = rename_arguments(err.args[0], names)
    if message == err.args[0]:
        return None
    try:
        new = (config_error_like(type(err)) if starts else type(err))(message)
    except Exception:  # a constructor that takes other arguments
        if not starts:
            return None
        new = ConfigError(message)
    for note in getattr(err, "__notes__", ()):
        add_note(new, note)
    return new


def add_note(err: BaseException, note: str) -> None:
    """``err.add_note(note)`` (Python >= 3.11; before, the note is kept in ``__notes__``
    as 3.11 does), once."""
    notes = getattr(err, "__notes__", None) or []
    if note in notes:
        return
    if hasattr(err, "add_note"):
        err.add_note(note)
    else:  # pragma: no cover - Python 3.10
        err.__notes__ = [*notes, note]


@contextmanager
def arguments_under(prefix: str, arguments: Arguments) -> Iterator[None]:
    """Errors raised inside by resireg's code that name one of ``arguments`` name
    ``<prefix>.<argument>`` instead (or ``arguments[argument]``: :func:`argument_names`):
    a function that passes its own argument on (``OtasEncoder(clip={...})`` building its
    CLIP from ``clip``) names it in the errors of the function it calls (``clip.weights=``)."""
    try:
        yield
    except Exception as err:
        new = renamed(err, argument_names(prefix, arguments))
        if new is None:
            raise
        raise new from err
