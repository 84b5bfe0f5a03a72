"""What a run may record, log or print of a secret: nothing. The one place that masks a URL's
password, finds URLs in free text (a command line, an error, a log line) and names the files
whose content is never copied into a record.

A tracking URI ``http://user:pass@host:5000`` or a study storage
``postgresql+psycopg://user:pass@db/optuna`` keeps the user and the host, which say where the
run went, and loses the password: ``http://user:***@host:5000``. Query parameters that carry a
credential (``?password=...``, ``?token=...``) are masked the same way. Environment variables
are never recorded at all, so they need no masking.
"""

from __future__ import annotations

import fnmatch
import logging
import re
from pathlib import PurePath
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

__all__ = [
    "MASK",
    "SECRET_FILE_PATTERNS",
    "SecretFilter",
    "looks_secret",
    "mask_text",
    "mask_url",
]

#: What stands in for a masked password or token.
MASK = "***"

#: Query parameters whose value is a credential (compared in lower case).
_SECRET_PARAMS = frozenset({
    "password", "passwd", "pwd", "pass", "token", "access_token", "auth", "secret",
    "api_key", "apikey", "key", "sig", "signature", "x-amz-signature", "sas", "credential",
})  # fmt: skip

#: A URL in free text: a scheme (``http``, ``postgresql+psycopg``, ``s3``...) and what follows
#: up to white space or a quote. Hand-written because no library finds URLs inside a command
#: line; each match is then taken apart by urllib.
_URL = re.compile(r"\b[a-zA-Z][a-zA-Z0-9+.\-]*://[^\s'\"<>]+")
#: A URL's ``user:password@`` wherever it stands: masked before urllib sees the text, so a
#: match urllib cannot take apart (Hydra's ``override_dirname`` joins overrides with ``,``, a
#: ``[`` makes urllib refuse the host) or that holds two URLs keeps no password either; a
#: multirun's overrides escape ``:`` (``http\://user\:pass@host``), so a ``\`` may precede it.
_USERINFO = re.compile(r"(\b[a-zA-Z][a-zA-Z0-9+.\-]*\\?://[^:/@\s'\"<>\\]*\\?):[^@/\s'\"<>]*@")

#: File names whose content is never inlined into a record (``code.diff``, a tracker's
#: artifacts), matched against every part of a path, case-insensitively.
SECRET_FILE_PATTERNS: tuple[str, ...] = (
    ".env", ".env.*", "*.env", ".envrc", ".netrc", ".pgpass", ".git-credentials", ".npmrc",
    ".pypirc", ".htpasswd", "*.pem", "*.key", "*.p12", "*.pfx", "*.jks", "*.keystore",
    "id_rsa*", "id_dsa*", "id_ecdsa*", "id_ed25519*", "*secret*", "*token*", "*password*",
    "*passwd*", "*credential*", "*apikey*", "*api_key*", ".aws", ".ssh", ".gnupg", ".docker",
    ".kube", "*.kdbx",
)  # fmt: skip


def mask_url(url: str) -> str:
    """``url`` with the password of its user part and the values of credential query
    parameters replaced by ``***``; anything that is not a URL comes back unchanged."""
    try:
        parts = urlsplit(url)
    except ValueError:  # not a URL urllib can take apart: its user part masked all the same
        return _USERINFO.sub(rf"\1:{MASK}@", url)
    if not parts.scheme or not parts.netloc:
        return url
    netloc = parts.netloc
    userinfo, at, host = netloc.rpartition("@")
    if at:
        user, colon, _password = userinfo.partition(":")
        netloc = f"{user}:{MASK}@{host}" if colon else f"{user}@{host}"
    query = parts.query
    if query:
        pairs = parse_qsl(query, keep_blank_values=True)
        if any(k.lower() in _SECRET_PARAMS for k, _ in pairs):
            masked = [(k, MASK if k.lower() in _SECRET_PARAMS else v) for k, v in pairs]
            query = urlencode(masked, safe="*")
    return urlunsplit((parts.scheme, netloc, parts.path, query, parts.fragment))


def mask_text(text: str) -> str:
    """``text`` with every URL in it masked by :func:`mask_url` (a command line, an error
    message, a config value)."""
    if "://" not in text:
        return text
    return _URL.sub(lambda m: mask_url(m.group(0)), _USERINFO.sub(rf"\1:{MASK}@", text))


def looks_secret(path: str | PurePath) -> bool:
    """Whether any part of ``path`` (a file or a folder above it) matches
    :data:`SECRET_FILE_PATTERNS`: its content is never copied into a record."""
    parts = PurePath(path).parts
    return any(
        fnmatch.fnmatch(part.lower(), pattern) for part in parts for pattern in SECRET_FILE_PATTERNS
    )


class SecretFilter(logging.Filter):
    """A logging filter that masks URLs in every record's message (its arguments formatted
    first), for the handlers of the console and the run's log file."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        masked = mask_text(message)
        if masked != message:
            record.msg, record.args = masked, None
        return True
