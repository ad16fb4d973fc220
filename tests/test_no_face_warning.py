"""Issue 44: rows without a face are never predicted silently. ``aumesh.predict_mesh`` warns once a call
(:class:`aumesh.NoFaceWarning`, one line) with the number of such rows, however they come (numbers, a mapping-free
array, a py-feat table's FaceScore 0); a row only partly NaN stays an error naming its row and column."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

import aumesh
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS
from test_predict_fex import N_ROWS, NO_FACE_ROW, fex_table, write_release


def _caught(call) -> tuple[object, list[warnings.WarningMessage]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = call()
    return out, [w for w in caught if issubclass(w.category, aumesh.NoFaceWarning)]


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    return aumesh.load_release(write_release(tmp_path_factory.mktemp("release")))


def test_one_row_of_nan_warns_that_it_has_no_face(release):
    mesh, caught = _caught(lambda: aumesh.predict_mesh(release, np.full(20, np.nan)))
    assert mesh.shape == (478, 3) and np.isnan(mesh).all()
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "\n" not in message and message.startswith("aus: 1 of 1 row(s) without a face")
    assert caught[0].filename == __file__  # points at the caller's line, as InputRangeWarning does


@pytest.mark.parametrize("n, blank", [(7, [0]), (40, [3, 4, 17, 39]), (5, [0, 1, 2, 3, 4])])
def test_a_batch_warns_once_with_its_count_of_rows_without_a_face(release, n, blank):
    rng = np.random.default_rng(n)
    x = rng.uniform(0.0, 1.0, (n, 23))
    x[:, 20:] = rng.uniform(-0.2, 0.2, (n, 3))
    x[blank] = np.nan  # py-feat's row for a frame without a face: every AU and pose value NaN
    meshes, caught = _caught(lambda: aumesh.predict_mesh(release, x))
    flagged = np.isnan(meshes).all(axis=(1, 2))
    np.testing.assert_array_equal(np.flatnonzero(flagged), blank)
    assert len(caught) == 1 and str(caught[0].message).startswith(f"aus: {len(blank)} of {n} row(s) without a face")
    # the same rows as a DataFrame of input columns: the same count
    _, caught = _caught(lambda: aumesh.predict_mesh(release, pd.DataFrame(x, columns=list(INPUT_COLUMNS))))
    assert len(caught) == 1 and f"{len(blank)} of {n} row(s)" in str(caught[0].message)


def test_every_row_with_a_face_is_silent(release):
    x = np.random.default_rng(1).uniform(0.0, 0.5, (9, 20))
    _, caught = _caught(lambda: aumesh.predict_mesh(release, x))
    assert caught == []


def test_a_py_feat_table_counts_its_faceScore_0_rows_too(release):
    df = fex_table("mp", np.random.default_rng(2))
    df.loc[1, "FaceScore"] = 0.0  # values left in the row, but py-feat says no face
    meshes, caught = _caught(lambda: aumesh.predict_mesh(release, df))
    expected = np.isin(np.arange(N_ROWS), [1, NO_FACE_ROW])
    np.testing.assert_array_equal(np.isnan(meshes).all(axis=(1, 2)), expected)
    assert len(caught) == 1 and f"{int(expected.sum())} of {N_ROWS} row(s) without a face" in str(caught[0].message)


def test_a_row_only_partly_nan_is_still_an_error_naming_row_and_column(release):
    x = np.random.default_rng(3).uniform(0.0, 1.0, (4, 20))
    x[2, :19] = np.nan  # all but AU43: not a frame without a face
    with pytest.raises(aumesh.PredictionInputError, match=rf"first in '{AU_COLUMNS[0]}' at row 2\. .*only partly NaN"):
        aumesh.predict_mesh(release, x)
