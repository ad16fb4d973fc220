"""An NPZ written array by array, each array's rows a chunk at a time: ``np.load`` reads it as ``np.savez``'s.

``np.savez`` needs every array whole in memory; a table of a million meshes is 5.7 GB of float32. An NPZ is an
uncompressed zip (``ZIP_STORED``, ZIP64) of ``.npy`` entries, and an ``.npy`` is a header (dtype, shape) followed by
the C-order bytes: knowing an array's shape up front, its rows can be written as they come, one entry after the
other. The entries and headers are numpy's own (``numpy.lib.format``), as ``np.savez`` writes them.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

import numpy as np
from numpy.lib import format as npy_format


class NpzStream:
    """A new NPZ file at ``path`` (opened for writing, closed by :meth:`close` or the ``with`` block).

    >>> with NpzStream(tmp) as npz:                                      # doctest: +SKIP
    ...     with npz.array("meshes", np.float32, (n, 478, 3)) as rows:
    ...         for chunk in chunks:
    ...             rows.write(chunk)
    ...     npz.add("no_face", no_face)
    """

    def __init__(self, path: str | Path) -> None:
        self._zip = zipfile.ZipFile(path, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True)

    @contextmanager
    def array(self, name: str, dtype: np.dtype | type, shape: tuple[int, ...]) -> Iterator[_Rows]:
        """An entry ``<name>.npy`` of ``dtype`` and ``shape``, its rows written through the yielded writer in order;
        fewer or more rows than ``shape[0]`` raise ``ValueError`` (the file would not load)."""
        dtype = np.dtype(dtype)
        if dtype.hasobject:
            raise ValueError(f"{name}: object arrays cannot be streamed (numpy pickles them)")
        header = {"descr": npy_format.dtype_to_descr(dtype), "fortran_order": False, "shape": tuple(shape)}
        with self._zip.open(f"{name}.npy", mode="w", force_zip64=True) as fh:
            npy_format.write_array_header_1_0(fh, header)  # np.save's own header (version 1.0: shapes fit)
            rows = _Rows(fh, dtype, tuple(shape))
            yield rows
            if rows.written != (shape[0] if shape else 1):
                raise ValueError(f"{name}: {rows.written} row(s) written of the {shape[0] if shape else 1} declared")

    def add(self, name: str, values: np.ndarray) -> None:
        """A whole (small) array as its entry, as ``np.savez`` writes it."""
        values = np.asanyarray(values)
        with self.array(name, values.dtype, values.shape) as rows:
            rows.write(values if values.ndim else values.reshape(1))

    def close(self) -> None:
        self._zip.close()

    def __enter__(self) -> NpzStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Rows:
    """The row writer of one entry: :meth:`write` appends rows of the entry's dtype and row shape."""

    def __init__(self, fh: IO[bytes], dtype: np.dtype, shape: tuple[int, ...]) -> None:
        self._fh, self._dtype, self._row = fh, dtype, shape[1:]
        self.written = 0

    def write(self, rows: np.ndarray) -> None:
        """Append ``rows`` (shape ``(k, *row_shape)``), converted to the entry's dtype."""
        rows = np.asarray(rows)
        if rows.shape[1:] != self._row and rows.size:
            raise ValueError(f"rows of shape {rows.shape[1:]} written to an entry of rows {self._row}")
        data = np.ascontiguousarray(rows, dtype=self._dtype)
        self._fh.write(memoryview(data.data).cast("B") if data.size else b"")  # no copy (tobytes: one more)
        self.written += len(rows)


__all__ = ["NpzStream"]
