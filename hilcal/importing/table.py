"""One input CSV as text cells with their file line numbers, and its mapped columns parsed as numbers.

Loggers write preambles, semicolons and decimal commas; the mapping's [csv] section says how. Every error names
the file, the line (1-based, as an editor shows it) and the column's header name.
"""

from __future__ import annotations

import csv
import difflib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilcal.importing.errors import ImportFileError
from hilcal.importing.mapping import CsvMap


@dataclass(frozen=True)
class Table:
    """The header and data rows of one file, every row with the line it starts on."""

    source: str
    header: tuple[str, ...]
    header_line: int
    rows: tuple[tuple[str, ...], ...]
    lines: tuple[int, ...]
    decimal: str = "."

    @property
    def name(self) -> str:
        """The file name without its folder (what --hold-out file:NAME matches)."""
        return Path(self.source).name

    @property
    def n(self) -> int:
        return len(self.rows)

    def error(self, row: int | None, column: str | None, detail: str) -> ImportFileError:
        """An ImportFileError at a data row (None: the header) and column."""
        line = self.header_line if row is None else self.lines[row]
        return ImportFileError(self.source, detail, line=line, column=column)

    def index(self, column: str) -> int:
        """Position of a header name; a missing or repeated name is an error that suggests close matches."""
        hits = [k for k, name in enumerate(self.header) if name == column]
        if len(hits) > 1:
            raise self.error(None, column, f"the header names this column {len(hits)} times")
        if not hits:
            close = difflib.get_close_matches(column, self.header, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else f"; the header has {', '.join(self.header)}"
            raise self.error(None, column, f"no such column in the header{hint}")
        return hits[0]

    def texts(self, column: str) -> list[str]:
        """The stripped cells of one column."""
        k = self.index(column)
        return [row[k].strip() for row in self.rows]

    def numbers(self, columns: list[str], *, allow_empty_rows: bool = False) -> np.ndarray:
        """(n, len(columns)) floats; empty, non-numeric, NaN or infinite cells are errors.

        With allow_empty_rows, a row whose cells in these columns are all empty gives NaN (a value not recorded).
        """
        out = np.empty((self.n, len(columns)))
        cells = [self.texts(c) for c in columns]
        for i in range(self.n):
            row = [col[i] for col in cells]
            if allow_empty_rows and all(t == "" for t in row):
                out[i] = np.nan
                continue
            for k, text in enumerate(row):
                out[i, k] = self._number(i, columns[k], text, partly=allow_empty_rows)
        return out

    def _number(self, row: int, column: str, text: str, *, partly: bool) -> float:
        if text == "":
            why = "a number is required" if not partly else "the other columns of this group have values"
            raise self.error(row, column, f"empty cell; {why}")
        value_text = text.replace(",", ".") if self.decimal == "," else text
        try:
            value = float(value_text)
        except ValueError:
            raise self.error(row, column, f"{text!r} is not a number") from None
        if math.isnan(value):
            raise self.error(row, column, f"{text!r}: NaN is not a measurement (remove the row or fill the value)")
        if not math.isfinite(value):
            raise self.error(row, column, f"{text!r} is not finite")
        return value


def read_table(path: str | Path, options: CsvMap | None = None) -> Table:
    """Read a CSV file: skip the lines above the header, skip blank lines, check every row's cell count."""
    options = options or CsvMap()
    source = str(path)
    header: list[str] | None = None
    header_line = options.header_line
    rows: list[tuple[str, ...]] = []
    lines: list[int] = []
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh, delimiter=options.delimiter)
            start = 1
            for cells in reader:
                line, start = start, reader.line_num + 1
                if line < options.header_line or not any(c.strip() for c in cells):
                    continue
                if header is None:
                    header, header_line = [c.strip() for c in cells], line
                    continue
                if len(cells) != len(header):
                    column = header[len(cells)] if len(cells) < len(header) else None
                    raise ImportFileError(
                        source, f"the row has {len(cells)} cells but the header (line {header_line}) has {len(header)}"
                        f" (delimiter {options.delimiter!r})", line=line, column=column)
                rows.append(tuple(cells))
                lines.append(line)
    except OSError as err:
        raise ImportFileError(source, f"cannot read: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ImportFileError(source, f"not a UTF-8 text file: {err.reason}") from None
    except csv.Error as err:
        raise ImportFileError(source, f"not a valid CSV file: {err}") from None
    if header is None:
        raise ImportFileError(source, f"no header row at or after line {options.header_line}", line=header_line)
    if not rows:
        raise ImportFileError(source, "the file has a header but no data rows", line=header_line)
    return Table(source=source, header=tuple(header), header_line=header_line, rows=tuple(rows),
                 lines=tuple(lines), decimal=options.decimal)
