"""``aumesh info`` and ``aumesh --version``: the versions of aumesh, python and the libraries that shape results,
from the installed package metadata."""

from __future__ import annotations

#: What ``aumesh --version --verbose`` and ``aumesh info`` list after aumesh itself (distribution names, as pip has them).
VERSION_LIBRARIES = (
    "dvc",
    "mlflow",
    "hydra-core",
    "dask",
    "distributed",
    "numpy",
    "scipy",
    "scikit-learn",
    "pandas",
    "pyarrow",
)


def versions(libraries: tuple[str, ...] = VERSION_LIBRARIES) -> dict[str, str]:
    """``{"aumesh": ..., "python": ..., <dist>: ...}`` from the installed package metadata (``importlib.metadata``).

    A library that is not installed is ``"not installed"``; aumesh without metadata (a source tree on
    ``PYTHONPATH`` only) falls back to ``aumesh.__version__``.
    """
    import platform
    from importlib import metadata

    def one(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    out = {"aumesh": one("aumesh")}
    if out["aumesh"] == "not installed":
        from aumesh import __version__

        out["aumesh"] = __version__
    out["python"] = platform.python_version()
    return out | {dist: one(dist) for dist in libraries}


def print_versions(verbose: bool) -> None:
    """``aumesh VERSION`` on stdout; with ``verbose``, python's and each library's below (:func:`versions`)."""
    found = versions()
    print(f"aumesh {found.pop('aumesh')}")
    if verbose:
        width = max(map(len, found))
        for dist, ver in found.items():
            print(f"  {dist:<{width}}  {ver}")


def _cmd_info(args) -> int:
    print_versions(verbose=True)
    return 0


def add_parser(subparsers) -> None:
    """Add ``info`` to the ``aumesh`` command."""
    p = subparsers.add_parser(
        "info",
        help="versions of aumesh, python and the libraries that shape results (dvc, mlflow, "
        "hydra-core, dask, numpy, ...), from the installed package metadata",
    )
    p.set_defaults(func=_cmd_info)
