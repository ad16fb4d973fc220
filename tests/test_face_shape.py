"""The shape guard: a release whose AU=0 face is flat (z left in a detector's crop units) is refused, one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.core.schema import flatten_axis_major
from aumesh.geometry import face, measures
from aumesh.model.face_shape import DEPTH_WIDTH_RANGE, au0_face, face_shape_error
from aumesh.model.release_check import ReleaseError
from aumesh.pipeline.release import refuse_implausible_face
from test_faults import mlflow_runs, run_cli, tree_digest


def _flattened(mesh: np.ndarray, factor: float) -> np.ndarray:
    """``mesh`` with its depth (the face frame's z) scaled by ``factor``, everything else as it was."""
    origin, axes, _ = face.face_frame(mesh)
    local = (mesh - origin) @ axes.T
    local[:, 2] *= factor
    return local @ axes + origin


def test_face_proportions_are_the_extents_of_the_surface_in_any_pose_and_units():
    tpl = face.canonical_template()  # already in the face frame: its own extents are the independent answer
    extent = np.ptp(tpl[:468], axis=0)
    R = Rotation.from_euler("xyz", [0.3, -0.5, 2.0]).as_matrix()
    posed = 57.0 * tpl @ R.T + np.array([300.0, -20.0, 5.0])  # pixels, turned, moved
    got = measures.face_proportions(posed)
    assert got["depth_width"] == pytest.approx(extent[2] / extent[0], rel=1e-9)
    assert got["width_height"] == pytest.approx(extent[0] / extent[1], rel=1e-9)
    squashed = measures.face_proportions(_flattened(posed, 1e-3))
    assert squashed["depth_width"] == pytest.approx(1e-3 * got["depth_width"], rel=1e-6)
    assert squashed["width_height"] == pytest.approx(got["width_height"], rel=1e-9)


def test_flat_face_is_refused_naming_file_ratio_range_and_cause_and_a_face_passes():
    tpl = 120.0 * face.canonical_template() + 300.0
    low, high = DEPTH_WIDTH_RANGE
    assert face_shape_error(measures.face_proportions(tpl)["depth_width"], "the AU=0 face", "m.npz") is None
    ratio = measures.face_proportions(_flattened(tpl, 1e-3))["depth_width"]
    msg = face_shape_error(ratio, "the AU=0 face (intercept)", "build/model/model.npz")
    assert msg is not None and "\n" not in msg
    for text in ("build/model/model.npz", f"{ratio:.4g}", f"[{low:g}, {high:g}]", "crop units", "mesh_units"):
        assert text in msg, (text, msg)
    deep = face_shape_error(5.0, "mean_aligned_mesh", "reference.npz")
    assert deep is not None and "larger units" in deep


def test_the_stage_check_names_the_reference_when_only_it_is_flat(tmp_path):
    tpl = 120.0 * face.canonical_template() + 300.0
    intercept = flatten_axis_major(tpl)
    record = refuse_implausible_face(intercept, tpl, tmp_path / "model.npz", tmp_path / "reference.npz")
    assert record["depth_width"] == pytest.approx(measures.face_proportions(tpl)["depth_width"], rel=1e-3)
    assert np.allclose(au0_face(intercept), tpl)
    with pytest.raises(ReleaseError, match=r"reference\.npz: mean_aligned_mesh has depth/width"):
        refuse_implausible_face(intercept, _flattened(tpl, 1e-3), tmp_path / "model.npz", tmp_path / "reference.npz")
    with pytest.raises(ReleaseError, match=r"model\.npz: the AU=0 face \(intercept\)"):
        flat = flatten_axis_major(_flattened(tpl, 1e-3))
        refuse_implausible_face(flat, tpl, tmp_path / "model.npz", tmp_path / "reference.npz")
    with pytest.raises(ReleaseError, match=r"model\.npz: the AU=0 face \(intercept\) .* is not a face"):
        refuse_implausible_face(np.zeros_like(intercept), tpl, tmp_path / "model.npz", tmp_path / "reference.npz")


def test_release_of_a_flat_model_exits_2_and_keeps_the_previous_release_bit_for_bit(workspace, capsys):
    card = json.loads((workspace / "release/model_card.json").read_text())
    shape = card["data"]["face_shape"]  # the good release records its face's proportions
    low, high = DEPTH_WIDTH_RANGE
    assert low < shape["depth_width"] < high and shape["width_height"] > 0.5
    md = (workspace / "release/MODEL_CARD.md").read_text()
    assert f"- Face shape (the AU=0 face): depth/width {shape['depth_width']:.3g}, width/height" in md
    before, runs = tree_digest(workspace / "release"), mlflow_runs(workspace)
    path = workspace / "build/model/model.npz"
    arrays = dict(np.load(path))
    face_px = au0_face(arrays["mesh_intercept"])
    arrays["mesh_intercept"] = flatten_axis_major(_flattened(face_px, 1e-3)).astype(arrays["mesh_intercept"].dtype)
    np.savez(path, **arrays)
    code, err = run_cli(["release"], workspace, capsys)
    assert code == 2, err
    assert err.startswith("aumesh release: error: ") and len(err.strip().splitlines()) == 1, err
    for text in ("build/model/model.npz", "AU=0 face", "depth/width", "crop units", "previous release is kept"):
        assert text in err, (text, err)
    assert tree_digest(workspace / "release") == before
    assert mlflow_runs(workspace).equals(runs)
