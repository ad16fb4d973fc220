"""A CSV's text when it is not what py-feat writes, named: one-line :class:`~aumesh.core.errors.TableError` s with the
file, the line (as a text editor counts it: the header is line 1) and the fix.

py-feat's ``detect(..., save=)`` writes ``DataFrame.to_csv(index=False)``: UTF-8 without a byte-order mark, ``,``
separators, ``.`` decimals, empty fields for NaN, one line per row. What else reaches ``data/``:

* **a byte-order mark** (Excel's "CSV UTF-8" writes one): accepted, the header is read as ``utf-8-sig``; a column name
  that still starts with one (a table converted from such a CSV without it) is named (:func:`check_names`);
* **``;`` or tab separators**, usually with **decimal commas** (Excel in a European locale): the header is one column
  whose name holds the separators (:func:`check_header_line`); a decimal comma in a ``,``-separated file is a quoted
  ``"0,5"`` that Arrow cannot read as a number (:func:`parse_error`);
* **a file cut mid-row** (an interrupted copy or export): its last line has fewer fields than the header;
* **NUL bytes** (a file preallocated or padded with zeros by a crash): :func:`check_bytes`, before Arrow parses them
  as text.

The readers (:mod:`aumesh.data.readers`: ingest, ``aumesh animate``; ``aumesh predict``'s header) call these where
they read a header or a range; the line of a range's row is :func:`first_line` + the row (py-feat writes no multi-line
fields).
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Sequence

from aumesh.core import storage
from aumesh.core.errors import TableError
from aumesh.core.storage import InputPath

BOM = "\ufeff"
#: Separators that Excel and other tools write instead of py-feat's ``,``.
OTHER_SEPARATORS = {";": "';'", "\t": "tab"}
DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d*,\d+(?:[eE][-+]?\d+)?\s*$")
_EXPECTED = re.compile(r"Expected (\d+) columns, got (\d+)")
_CONVERSION = re.compile(r"In CSV column #(\d+): CSV conversion error to (\w+): invalid value '(.*)'", re.S)
RESAVE = "pandas: pd.read_csv(path, sep=';', decimal=',').to_csv(path, index=False)"


def first_line(path: InputPath, offset: int, compressed: bool = False) -> int:
    """The line number (header = 1) of the line starting at byte ``offset`` of ``path`` (a gzipped CSV is read as
    one range after its header: line 2). Reads the file up to ``offset``: for error messages only."""
    if compressed:
        return 2
    lines, left = 1, offset
    with storage.open_input(path) as fh:
        while left > 0:
            chunk = fh.read(min(left, 16 << 20))
            if not chunk:
                break
            lines += chunk.count(b"\n")
            left -= len(chunk)
    return lines


def check_header_line(path: InputPath, line: str, second: str = "") -> None:
    """The header's first line (``utf-8-sig``-decoded: a BOM is already gone), refused when it holds NUL bytes or is
    separated by ``;`` or tabs instead of ``,``; ``second``: the next line, to tell decimal commas.

    Raises
    ------
    TableError
        Naming the file, line 1, what the line is and the fix.
    """
    if "\x00" in line:
        raise TableError(
            f"{path}: line 1 (the header) holds NUL bytes: not a CSV as py-feat writes it (a file padded with zeros "
            f"or a binary file named .csv). Fix: export it again with py-feat's detect(..., save=) or copy it again."
        )
    fields = next(csv.reader([line]), [])
    for sep, name in OTHER_SEPARATORS.items():
        if len(fields) <= 2 and line.count(sep) >= 2:
            decimals = any(DECIMAL_COMMA.match(v) for v in second.rstrip("\r\n").split(sep))
            raise TableError(
                f"{path}: line 1 (the header) is separated by {name}, not ',' (the CSV of a European-locale Excel"
                f"{', with decimal commas' if decimals else ''}): {line.count(sep) + 1} columns read as "
                f"{len(fields)}. Fix: save it with ',' separators and '.' decimals ({RESAVE})."
            )


def check_names(names: Sequence[str], where: str) -> None:
    """A table's column names refused when they are a CSV header misread: a name starting with a byte-order mark,
    or a single name holding ``;``/tab-separated names.

    Raises
    ------
    TableError
        Naming ``where``, what the names are and the fix.
    """
    marked = next((str(n) for n in names if str(n).startswith(BOM)), None)
    if marked is not None:
        raise TableError(
            f"{where}: column {marked!r} starts with a byte-order mark (U+FEFF, from a CSV saved as 'CSV UTF-8' by "
            f"Excel, read without it). Fix: read that CSV with encoding='utf-8-sig' (or give aumesh the CSV itself), "
            f"or rename the column to {marked[1:]!r}."
        )
    for sep, name in OTHER_SEPARATORS.items():
        if len(names) <= 2 and any(str(n).count(sep) >= 2 for n in names):
            raise TableError(
                f"{where}: the columns are separated by {name}, not ',' (the CSV of a European-locale Excel): "
                f"{len(names)} column(s) read. Fix: save it with ',' separators and '.' decimals ({RESAVE})."
            )


def check_bytes(path: InputPath, data: bytes, start_line: int | None, offset: int = 0) -> None:
    """A range of CSV bytes (starting at byte ``offset`` of ``path``, line ``start_line``; None: to be counted)
    refused when it holds NUL bytes, before Arrow reads them as text.

    Raises
    ------
    TableError
        Naming the file, the line and byte of the first NUL, and the fix.
    """
    at = data.find(b"\x00")
    if at < 0:
        return
    line = (first_line(path, offset) if start_line is None else start_line) + data.count(b"\n", 0, at)
    raise TableError(
        f"{path}: NUL bytes from line {line} (byte {offset + at:,}): the file is padded with zeros, likely an "
        f"interrupted write or copy. Fix: copy or export it again (if the rows before it are whole, cut the file at "
        f"byte {offset + at:,})."
    )


def _records(data: bytes) -> Sequence[tuple[int, list[str]]]:
    """(line offset of the record within ``data``, fields) of every record of ``data``."""
    reader = csv.reader(io.TextIOWrapper(io.BytesIO(data), encoding="utf-8", errors="replace", newline=""))
    line = 0
    out = []
    for fields in reader:
        out.append((line, fields))
        line = reader.line_num
    return out


def parse_error(
    path: InputPath, data: bytes, start_line: int, header: Sequence[str], message: str, columns: Sequence[str]
) -> TableError:
    """Arrow's refusal of a CSV range (``data``, starting at line ``start_line``) as one line naming the file, the line
    and what it is: a row cut short at the end of the file, a row of another width, a decimal comma, or a value that
    is not a number. ``message``: Arrow's first line."""
    width = _EXPECTED.search(message)
    if width:
        want = int(width.group(1))
        records = _records(data)
        for k, (at, fields) in enumerate(records):
            if len(fields) != want:
                line = start_line + at
                last = k == len(records) - 1
                if last and len(fields) < want and not data.endswith(b"\n"):
                    return TableError(
                        f"{path}: the file ends mid-row: line {line} has {len(fields)} of the header's {want} fields "
                        f"and no line end (cut short: an interrupted copy or export). Fix: copy or export it again, "
                        f"or delete line {line}."
                    )
                return TableError(
                    f"{path}: line {line} has {len(fields)} fields, the header {want}. Fix: write every row with "
                    f"the header's columns (py-feat's to_csv does; a ',' inside a value must be quoted)."
                )
    conversion = _CONVERSION.search(message)
    if conversion:
        k, typ, value = int(conversion.group(1)), conversion.group(2), conversion.group(3)
        name = header[k] if k < len(header) else f"#{k}"
        found = next((start_line + at for at, f in _records(data) if k < len(f) and f[k] == value), None)
        where = f" at line {found}" if found is not None else ""
        if DECIMAL_COMMA.match(value):
            return TableError(
                f"{path}: column {name!r} holds {value!r}{where}: a decimal comma (a European-locale export). Fix: "
                f"write '.' decimals (pandas: pd.read_csv(path, decimal=',').to_csv(path, index=False))."
            )
        return TableError(
            f"{path}: column {name!r} holds {value!r}{where}, not a {'whole ' if typ.startswith('int') else ''}"
            f"number. Fix: write numbers as numbers and missing values as empty fields or NaN (py-feat's to_csv does)."
        )
    column = next((c for c in columns if f"'{c}'" in message), None)
    return TableError(
        f"{path}: cannot read the CSV from line {start_line}{f' (column {column!r})' if column else ''}: {message[:200]}. "
        f"Fix: write numbers as numbers and missing values as empty fields or NaN (py-feat's to_csv does)."
    )
