"""Tokens: generation, hashing, constant-time checks, the operator (admin) token (the routes'
token dependencies are in ``server.api.deps``).

Tokens are 256-bit random secrets; only their SHA-256 is stored, so nobody (operators
included) can read a token back. Checks compare digests with ``hmac.compare_digest``.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
import stat
from pathlib import Path

from server.api.errors import api_error
from server.config import Settings

log = logging.getLogger("srd.security")

TOKEN_BYTES = 32  # 256 bits of entropy: a plain SHA-256 of it is a safe verifier
WEAK_TOKEN_CHARS = 16
"""An operator token shorter than this is named in the log at every start."""


def new_token(prefix: str) -> str:
    """A fresh high-entropy bearer token, e.g. ``srdp_...`` for participants."""
    return f"{prefix}_{secrets.token_urlsafe(TOKEN_BYTES)}"


def hash_token(token: str) -> str:
    """Hex SHA-256 of a token (what the database keeps)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def token_matches(token: str, stored_hash: str) -> bool:
    """Constant-time check of a presented token against a stored hash."""
    return hmac.compare_digest(hash_token(token), stored_hash)


def require_participant(token: str, stored_hash: str, participant: str) -> None:
    """403 naming the participant unless ``token`` is that participant's."""
    if not token_matches(token, stored_hash):
        raise api_error(
            403,
            f"the bearer token is not the token of participant {participant!r}",
            loc=("header", "Authorization"),
            kind="bad_token",
        )


def load_admin_token_hash(settings: Settings) -> str:
    """The hash of the operator token: ``SRD_ADMIN_TOKEN``, else the token file under
    ``data_dir`` (created with mode 0600 at first start)."""
    if settings.admin_token is not None:
        token = settings.admin_token.get_secret_value()
        if len(token) < WEAK_TOKEN_CHARS:
            log.warning("SRD_ADMIN_TOKEN has %d characters: a guess away from the operator's "
                        "rights (openssl rand -hex 32 makes a strong one)", len(token))  # fmt: skip
        return hash_token(token)
    path = settings.admin_token_file
    if not path.exists():
        _write_secret_file(path, new_token("srda"))
        log.warning("generated the admin token into %s (mode 0600)", path)
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        log.warning("the admin token file %s may be read by others (mode %04o): chmod 600 it",
                    path, mode)  # fmt: skip
    return hash_token(path.read_text().strip())


def _write_secret_file(path: Path, secret: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:  # another process created it first: use theirs
        return
    with os.fdopen(fd, "w") as handle:
        handle.write(secret + "\n")
