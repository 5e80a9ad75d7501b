"""The generator's one exception: a motion attempt that failed validation."""

from __future__ import annotations


class GenerationError(RuntimeError):
    """A motion attempt that failed validation (the generator retries with new draws)."""
