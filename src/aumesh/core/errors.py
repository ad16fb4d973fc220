"""The one exception family a user fixes (data, config, paths).

``aumesh`` prints a :class:`UserError`'s message on one or two lines and exits with status 2;
the traceback only with ``--debug`` (or ``AUMESH_DEBUG=1``). Anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations


class UserError(Exception):
    """Bad input, configuration or path; the message names the file, the column or key, and the fix."""


class ConfigError(UserError, ValueError):
    """A configuration key with a wrong type or value; the message names the key, the value and what is allowed."""


class TableError(UserError, ValueError):
    """A frame table that cannot be used as it is; the message says which file, which column and the fix."""


class MissingFileError(UserError, FileNotFoundError):
    """A file the user named does not exist; the message names it and how to get it."""


def corrupt_parquet(path, err: BaseException, what: str = "") -> TableError:
    """A parquet file pyarrow cannot read (``what``: which columns), with the fix."""
    first = str(err).splitlines()[0] if str(err) else ""
    return TableError(
        f"{path}: corrupt or truncated parquet file{what} ({type(err).__name__}: {first}). "
        f"Fix: restore the tracked copy (`dvc checkout --force`, or `dvc pull`) or re-export it with pandas.DataFrame.to_parquet."
    )


class CorruptFileError(UserError, ValueError):
    """A file on disk that is truncated, damaged or not what its checksum says; the message names it and the fix."""


class DiskFullError(UserError, OSError):
    """No space left on the device while writing an output; the message names the folder, what it needed and that
    the previous outputs are intact (every output is written atomically). ``errno`` stays ``ENOSPC``."""

    def __str__(self) -> str:  # the message alone, not OSError's "[Errno 28] ..."
        return str(self.strerror)


class NotWritableError(UserError, PermissionError):
    """An output folder (or ``params.yaml``'s) that cannot be written: read-only filesystem or no permission; the
    message names the folder and the fix. ``errno`` stays ``EACCES``/``EPERM``/``EROFS``."""

    def __str__(self) -> str:  # the message alone, not OSError's "[Errno 13] ..."
        return str(self.strerror)


class TruncatedFileError(CorruptFileError, EOFError):
    """A file that ends before its header says (an ``EOFError`` too, what the readers raised before)."""


class ClusterError(UserError):
    """A Dask cluster that cannot serve the run: no scheduler at the address, a scheduler lost mid-run, a worker that
    cannot read the data or write the output folders at the paths the stage uses; the message names the address or
    the worker and the path, and the fix."""


class DirectionCheckError(UserError, ValueError):
    """A release whose inputs do not move the face the way their names say (permuted or mirrored columns); the
    message names the release file, the suspected permutation or blendshape, and the fix."""
