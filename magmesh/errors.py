"""Errors a person can fix (a name, a flag, a file, an unreachable endpoint): the ``magmesh`` command prints
them as one paragraph and exits non-zero, never with a traceback."""

from __future__ import annotations


class UserError(Exception):
    """A mistake or condition the user can act on. ``str(e)`` is the paragraph shown; ``code`` the exit code."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


def known(names) -> str:
    """``a, b, c`` (sorted) or ``none``, for "known: ..." lists."""
    names = sorted(str(n) for n in names)
    return ", ".join(names) if names else "none"
