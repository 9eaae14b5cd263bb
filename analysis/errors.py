"""The project's one exception root and its few subclasses.

Every error the project raises on purpose derives from :class:`CdprError`, so a caller (and the CLI,
which turns them into one line and exit code 2) can catch them all at once.
"""

from __future__ import annotations


class CdprError(Exception):
    """Root of every error raised on purpose by cdpr."""


class InputError(CdprError, ValueError):
    """An argument has the wrong shape, unit or value.

    The message names what was expected and what came.
    """


class ConfigError(CdprError):
    """A configuration or data file is invalid.

    Parameters
    ----------
    source:
        The file (or other origin) that holds the bad value.
    key:
        The key, row or column at fault (may be empty).
    problem:
        What is wrong, in a few words.
    """

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = str(source)
        self.key = str(key)
        self.problem = str(problem)
        where = f"{self.source}: {self.key}: " if self.key else f"{self.source}: "
        super().__init__(where + self.problem)


class InfeasibleError(CdprError):
    """No tension distribution satisfies the equilibrium within the cable limits."""
