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


class ClusterError(UserError):
    """A Dask cluster that cannot serve the run: no scheduler at the address, a scheduler lost mid-run, a worker that
    cannot read the data or write the output folders at the paths the stage uses; the message names the address or
    the worker and the path, and the fix."""
