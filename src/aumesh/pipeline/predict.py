"""``aumesh predict``: a release applied to a table of AU (+ pose) rows, meshes written to a file.

Reads a CSV or parquet table (one row per mesh; columns named ``AU01 .. AU43``, missing AUs 0,
optionally ``Pitch``, ``Yaw``, ``Roll`` in radians), predicts with :func:`aumesh.predict_mesh` and
writes, by the output's suffix:

- ``.npz``: ``meshes`` (N, 478, 3) float32 in table row order, the inputs ``au`` (N, 20) and
  ``pose`` (N, 3) as the model used them, ``au_columns`` and ``pose_columns``;
- ``.obj`` / ``.ply``: one row only, the mesh with the project's triangulation
  (:func:`aumesh.geometry.face.triangulate`), triangles facing out of the face.

Files are written atomically.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from aumesh.data.schema import POSE_COLUMNS
from aumesh.export import meshfiles
from aumesh.geometry import face
from aumesh.model.inference import PredictionInputError, input_rows, load_release, predict_mesh
from aumesh.utils.errors import MissingFileError
from aumesh.utils.io import atomic_savez, atomic_write_text

log = logging.getLogger(__name__)

TABLE_SUFFIXES = (".csv", ".parquet")
MESH_SUFFIXES = (".obj", ".ply")
OUT_SUFFIXES = (".npz", *MESH_SUFFIXES)


def read_input_table(path: str | os.PathLike, ignore: Sequence[str] = ()) -> pd.DataFrame:
    """The model-input columns of a CSV or parquet table, ``ignore`` columns dropped.

    Raises
    ------
    FileNotFoundError
        No such file.
    PredictionInputError
        Unsupported suffix, an ``ignore`` column the table lacks, or no rows.
    """
    path = Path(path)
    if path.suffix.lower() not in TABLE_SUFFIXES:
        raise PredictionInputError(f"{path}: unsupported table type {path.suffix!r}; use {' or '.join(TABLE_SUFFIXES)}")
    if not path.is_file():
        raise MissingFileError(f"input table not found: {path}")
    df = pd.read_csv(path) if path.suffix.lower() == ".csv" else pd.read_parquet(path)
    absent = [c for c in ignore if c not in df.columns]
    if absent:
        raise PredictionInputError(f"{path}: --ignore names column(s) {absent} that the table does not have "
                                   f"(it has {list(df.columns)})")
    if df.empty:
        raise PredictionInputError(f"{path}: no rows to predict")
    return df.drop(columns=list(ignore))


def predict_table(release: str | os.PathLike, table: str | os.PathLike, out: str | os.PathLike,
                  ignore: Sequence[str] = ()) -> tuple[Path, int]:
    """Predict one mesh per table row and write them to ``out`` (``.npz``, or ``.obj`` / ``.ply`` for one row).

    Returns
    -------
    (Path, int)
        The file written and the number of meshes.

    Raises
    ------
    FileNotFoundError, ReleaseError, PredictionInputError
        A missing file, an unusable release, or table values the model cannot take (the message
        names the file and the column).
    """
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in OUT_SUFFIXES:
        raise PredictionInputError(f"--out {out}: unsupported suffix {out.suffix!r}; use {', '.join(OUT_SUFFIXES)}")
    arrays = load_release(release)
    df = read_input_table(table, ignore)
    try:
        au, pose, _ = input_rows(arrays, df)
    except PredictionInputError as exc:
        raise PredictionInputError(f"{table}: {exc}") from exc
    if suffix in MESH_SUFFIXES and len(df) != 1:
        raise PredictionInputError(f"{table} has {len(df)} rows; {suffix} holds one mesh. "
                                   f"Fix: write .npz, or give a one-row table")
    meshes = predict_mesh(arrays, au, pose)
    if suffix == ".npz":
        atomic_savez(out, meshes=meshes.astype(np.float32), au=au, pose=pose,
                     au_columns=np.asarray(arrays["au_columns"]), pose_columns=np.array(POSE_COLUMNS))
    else:
        mesh = meshes[0]
        tri = face.outward_triangles(mesh, face.triangulate(mesh))
        comment = f"aumesh predict: {Path(release).name}, row 0 of {Path(table).name}"
        text = meshfiles.obj_text(mesh, tri, comment) if suffix == ".obj" else meshfiles.ply_text(mesh, tri, comment)
        atomic_write_text(out, text)
    log.info("predicted %d mesh(es) from %s with %s -> %s", len(meshes), table, release, out)
    return out, len(meshes)
