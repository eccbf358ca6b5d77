"""Errors raised on bad survey input."""

from __future__ import annotations

from typing import Any


class SurveyFormatError(ValueError):
    """A survey file or field does not hold what it must.

    The message is one line: file, field, expected, found.
    """

    def __init__(self, file: Any, field: str, expected: str, found: Any) -> None:
        self.file, self.field, self.expected, self.found = str(file), field, expected, found
        super().__init__(f"{file}: field '{field}': expected {expected}, found {found}")
