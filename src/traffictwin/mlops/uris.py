"""Credentials in URIs never reach a message: :func:`mask_uri` for one URI, :func:`mask_secrets`
for any text that may hold URIs (an exception's message, a log line).

A tracking URI may carry a password (``postgresql://user:secret@host/db``) or a token in its
query (``...?token=...``). Every message of :mod:`traffictwin.mlops`, the registry commands and the
promotion workflow that names a URI passes it through one of these: the password and secret
query values become ``***``; user, host, port, path and other query keys stay (they say which
registry is meant).
"""

from __future__ import annotations

import re

MASK = "***"
#: query keys whose values are secrets (compared case-insensitively)
SECRET_KEYS = (
    "password",
    "passwd",
    "pwd",
    "token",
    "access_token",
    "secret",
    "api_key",
    "apikey",
    "key",
    "sig",
    "signature",
)
# scheme://user:password@ -> the password (up to the last '@' before the path)
_USERINFO = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s/:@]*:)(?P<pw>[^\s/]*)(?=@)")
_QUERY = re.compile(
    r"(?P<head>[?&;](?:" + "|".join(SECRET_KEYS) + r")=)(?P<val>[^&;#\s'\"]*)", re.IGNORECASE
)


def mask_secrets(text: str) -> str:
    """``text`` with the password of every ``scheme://user:password@`` and the value of every
    secret query parameter (:data:`SECRET_KEYS`) replaced by ``***``."""
    text = _USERINFO.sub(lambda m: m.group("head") + MASK, str(text))
    return _QUERY.sub(lambda m: m.group("head") + MASK, text)


def mask_uri(uri: str | None) -> str:
    """One URI for a message (:func:`mask_secrets`); ``"None"`` for None."""
    return mask_secrets(str(uri))
