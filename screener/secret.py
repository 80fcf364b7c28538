"""A deployment's screener secret: which reference populations and test-auction seeds it gives
(``screener.impact``), said without saying the secret. Plain hashing, no tensors: the API process
reads it at start without loading the screener's judging code."""

from __future__ import annotations

import hashlib
import hmac
import unicodedata

from screener import limits

SECRET_VARIABLE = "SRD_SCREENER_SECRET"
"""The environment variable holding a deployment's secret: when set, the reference populations
and the test auctions' seeds are drawn from it as well as from ``IMPACT_SEED``, so that a model
tuned offline against the public screener's populations meets others (docs/screener.md)."""

PUBLIC = "public"
"""The populations marker of a screener without a secret."""


def secret_bytes(secret: str) -> bytes:
    """A secret as it is hashed: without surrounding white space (a secret file's newline),
    in Unicode's NFC form, in UTF-8 (bytes the environment could not decode kept as they
    were)."""
    return unicodedata.normalize("NFC", secret.strip()).encode("utf-8", "surrogateescape")


def seed_words_of(secret: str) -> tuple[int, ...]:
    """The entropy of the reference populations and test auctions under ``secret``:
    ``IMPACT_SEED``, then four 32-bit words of the secret's SHA-256 (none for no secret)."""
    if not secret.strip():
        return (limits.IMPACT_SEED,)
    digest = hashlib.sha256(secret_bytes(secret)).digest()
    return (
        limits.IMPACT_SEED,
        *(int.from_bytes(digest[i : i + 4], "big") for i in range(0, 16, 4)),
    )


def marker_of(secret: str) -> str:
    """Which populations ``secret`` gives, without saying the secret: ``public``, or 16 hex
    digits of an HMAC keyed by it. Evidence carries it, so two verdicts say whether the same
    populations made them."""
    if not secret.strip():
        return PUBLIC
    return hmac.new(secret_bytes(secret), b"srd-screener-populations", "sha256").hexdigest()[:16]
