"""Errors a user can cause. The CLI turns each into one line and a non-zero exit."""


class RelocfwError(Exception):
    """Base class for problems with the user's input, config or files (not bugs)."""


class ConfigError(RelocfwError, ValueError):
    """An option has an impossible value; the message names the key."""


class DataError(RelocfwError):
    """A file is missing, unreadable or holds something that is not what it should be."""
