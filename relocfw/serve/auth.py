"""The optional bearer token (serve.token_file): callers send
`Authorization: Bearer TOKEN`; compared in constant time."""

from __future__ import annotations

import hmac
from pathlib import Path

from relocfw.core.errors import ConfigError

# Shorter tokens are guessable by trying; 16 characters of a random hex or base64
# token are 64 bits or more.
MIN_TOKEN_LENGTH = 16


class BearerToken:
    """The token read from serve.token_file, and the check of a request's header."""

    def __init__(self, token: str) -> None:
        self._expected = token.encode()

    @classmethod
    def from_file(cls, path: Path) -> BearerToken:
        """The file's text without surrounding whitespace (a trailing newline).

        Raises:
            ConfigError: naming serve.token_file: missing, unreadable, or a token
                shorter than MIN_TOKEN_LENGTH characters or with inner whitespace.
        """
        try:
            token = Path(path).read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError(f"serve.token_file={path}: cannot read it ({error})") from error
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
