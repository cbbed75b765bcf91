"""Secrets the service must read back, sealed at rest: a copy of the database does not give them.

A webhook's signing secret must be read to sign each delivery, so it cannot be hashed as API keys
are; stored as given, anyone with a backup could sign events the organisation's systems would
act on. It is stored sealed instead, with Fernet (AES-128-CBC and HMAC-SHA256, from the
``cryptography`` package) under the server's keys: ``NARXWATCH_SECRET_KEYS``, the first sealing and
every one unsealing, so that a key is rotated by putting a new one first (``narxwatch db reseal``
then seals every secret with it, and the old key may go). Without that setting the keys are read
from ``NARXWATCH_SECRET_KEY_FILE`` (one a line), which the first process to need it creates,
readable by its owner alone: the embedded default needs no setup, and processes on other
machines (workers) must be given the same keys.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from functools import cache
from pathlib import Path

from cryptography.fernet import Fernet, InvalidToken, MultiFernet

from service.config import KEY_FORM, Settings, is_key
from service.errors import SettingsError


class UnsealError(Exception):
    """A sealed secret none of the server's keys opens."""

    def __init__(self) -> None:
        super().__init__(
            "the secret was sealed under a key this server does not hold: give it the key it was "
            "sealed with (NARXWATCH_SECRET_KEYS or NARXWATCH_SECRET_KEY_FILE)"
        )


def seal(secret: str, settings: Settings) -> str:
    """``secret`` sealed under the first of the server's keys (a Fernet token, ASCII)."""
    return _keys(settings).encrypt(secret.encode()).decode("ascii")


def unseal(token: str, settings: Settings) -> str:
    """The secret ``token`` seals; :class:`UnsealError` when no key of the server's opens it."""
    return _opened(_keys(settings).decrypt, token).decode()


def reseal(token: str, settings: Settings) -> str:
    """``token`` sealed again under the first key (a rotation); :class:`UnsealError` as unseal."""
    return _opened(_keys(settings).rotate, token).decode("ascii")


def _opened(opening: Callable[[bytes], bytes], token: str) -> bytes:
    """``opening`` (which must open the token first) applied to ``token``, or UnsealError."""
    try:
        return opening(token.encode("ascii"))
    except (InvalidToken, UnicodeEncodeError) as exc:
        raise UnsealError from exc


def check_keys(settings: Settings) -> None:
    """Read the server's keys now (making the key file where there is none), so that a process
    started with keys it cannot read fails at its start (:class:`SettingsError`), not at its
    first webhook."""
    _keys(settings)


def _keys(settings: Settings) -> MultiFernet:
    if settings.secret_keys:
        return _fernets(tuple(key.get_secret_value() for key in settings.secret_keys))
    return _fernets(tuple(_key_file(settings.secret_key_file)))


@cache
def _fernets(keys: tuple[str, ...]) -> MultiFernet:
    return MultiFernet([Fernet(key) for key in keys])


def _key_file(path: Path) -> list[str]:
    """The keys in ``path``, one a line; a new key there first if the file does not exist.

    Made whole under another name and linked into place, so that of processes starting together
    one key wins and every other reads it complete, never a half-written file."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        descriptor, draft = tempfile.mkstemp(dir=path.parent, prefix=".secret-key-")  # mode 0600
        try:
            with os.fdopen(descriptor, "wb") as file:
                file.write(Fernet.generate_key() + b"\n")
            os.link(draft, path)
        except FileExistsError:
            pass  # another process made it first: its key is the one
        finally:
            os.unlink(draft)
    keys = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    if not keys or not all(is_key(key) for key in keys):
        raise SettingsError(f"NARXWATCH_SECRET_KEY_FILE: {path} must hold one key a line, each {KEY_FORM}")
    return keys
