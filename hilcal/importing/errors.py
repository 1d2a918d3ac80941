"""The one error of an import: bad input, named by its file, line and column (the CLI exits with code 2 on it)."""

from __future__ import annotations


class ImportFileError(ValueError):
    """An input that cannot be imported; ``line`` is the 1-based line of the file, ``column`` a header name.

In a mapping or geometry file ``column`` holds the key and ``label`` is "key".
"""

    def __init__(
        self, source: str, detail: str, *, line: int | None = None, column: str | None = None, label: str = "column"
    ) -> None:
        place = source if line is None else f"{source} line {line}"
        super().__init__(f"{place}, {label} {column}: {detail}" if column else f"{place}: {detail}")
        self.source = source
        self.line = line
        self.column = column
        self.detail = detail


class ValueProblem(ValueError):
    """A value that does not fit, found by a pure conversion: ``row`` and ``column`` index the arrays it was given.

    The importer turns it into an ImportFileError naming the file, line and header name of that cell.
    """

    def __init__(self, row: int, column: int, detail: str) -> None:
        super().__init__(detail)
        self.row = row
        self.column = column
        self.detail = detail
