"""The front end's error: a problem with what the user asked for, printed as one line."""

from __future__ import annotations


class UsageError(ValueError):
    """A problem with what the user asked for; printed as one line."""
