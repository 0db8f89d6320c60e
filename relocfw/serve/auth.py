"""The optional bearer token (serve.token_file): callers send
`Authorization: Bearer TOKEN`; compared in constant time."""

from __future__ import annotations

import hmac
import os
import stat
from pathlib import Path

from relocfw.core.errors import ConfigError

# Shorter tokens are guessable by trying; 16 characters of a random hex or base64
# token are 64 bits or more.
MIN_TOKEN_LENGTH = 16
# Permission bits that give the file's group or other users any access: a token they
# can read is theirs too. ssh refuses a private key with any of them set, and so does
# this (POSIX only: Windows has no such bits).
SHARED_BITS = stat.S_IRWXG | stat.S_IRWXO


class BearerToken:
    """The token read from serve.token_file, and the check of a request's header."""

    def __init__(self, token: str) -> None:
        self._expected = token.encode()

    @classmethod
    def from_file(cls, path: Path) -> BearerToken:
        """The file's text without surrounding whitespace (a trailing newline).

        Raises:
            ConfigError: naming serve.token_file: missing, unreadable, readable by
                other users (group or others have any permission: chmod 600), or a
                token shorter than MIN_TOKEN_LENGTH characters or with inner whitespace.
        """
        try:
            token = Path(path).read_text(encoding="utf-8").strip()
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError(f"serve.token_file={path}: cannot read it ({error})") from error
        if os.name == "posix" and mode & SHARED_BITS:
            raise ConfigError(
                f"serve.token_file={path}: other users may read it (mode {mode:o}); "
                f"make it the service user's alone: chmod 600 {path} (a mounted secret: "
                "a Kubernetes Secret's `defaultMode: 0400`, a Docker secret's `mode: 0400` "
                "with the service's `uid`)"
            )
        if len(token) < MIN_TOKEN_LENGTH or any(c.isspace() for c in token):
            raise ConfigError(
                f"serve.token_file={path}: the token must be one word of at least "
                f"{MIN_TOKEN_LENGTH} characters (e.g. `openssl rand -hex 32 > {path}`)"
            )
        return cls(token)

    def allows(self, authorization: str | None) -> bool:
        """Whether an Authorization header carries the token. hmac.compare_digest
        takes the same time wherever the first wrong byte is, so the answer's timing
        tells a caller nothing about how much of a guess was right."""
        scheme, _, given = (authorization or "").partition(" ")
        if scheme.lower() != "bearer":
            return False
        return hmac.compare_digest(given.strip().encode(), self._expected)
