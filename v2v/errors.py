"""User-facing errors.

Every mistake a user can make (bad scenario field, missing file, unreadable RINEX...)
is raised as :class:`UserError`. The CLI prints it as a single line and exits with
status 2; it never shows a traceback for these.
"""

from __future__ import annotations


class UserError(Exception):
    """A user's input is wrong. ``field`` names what is wrong, ``fix`` says what to do."""

    def __init__(self, message: str, *, field: str | None = None, fix: str | None = None):
        self.field = field
        self.fix = fix
        self.message = message
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = []
        if self.field:
            parts.append(f"{self.field}: {self.message}")
        else:
            parts.append(self.message)
        if self.fix:
            parts.append(f"fix: {self.fix}")
        return " -- ".join(parts).replace("\n", " ")
