"""The family releases' NPZ (issue 46, contract item 3): py-feat's ``PLSFeatMeshModel`` keys, the frame, the round trip.

The independent route is py-feat 2.1.5's own code, transcribed here (``feat/plotting.py``
``_load_pls_feat_to_mesh_from_hub`` + ``PLSFeatMeshModel.predict``): it reads ``coef`` whole, keeps its first
``len(feature_columns)`` rows, and predicts ``x @ coef[:k] + intercept``. The family fit is a real PLS fit
(:class:`aumesh.model.pls.PLSRegression`) of synthetic meshes on the family's design, written as the evaluate stage
writes ``build/families/<family>/model.npz``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS, FAMILIES, feature_set_columns
from aumesh.core.schema import N_TARGETS, flatten_axis_major
from aumesh.geometry.frame import canonical_frame, rotate_axis_major
from aumesh.model import family_release, support
from aumesh.model.pls import PLSRegression
from aumesh.synthetic.family_truth import draw_family_values, family_fields
from conftest import face_reference, seeded_rng

# py-feat 2.1.5 feat/utils/__init__.py, copied as text (not imported from aumesh): the lists its loader requires
PYFEAT_MP_BLENDSHAPE_NAMES = """_neutral browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight
cheekPuff cheekSquintLeft cheekSquintRight eyeBlinkLeft eyeBlinkRight eyeLookDownLeft eyeLookDownRight eyeLookInLeft
eyeLookInRight eyeLookOutLeft eyeLookOutRight eyeLookUpLeft eyeLookUpRight eyeSquintLeft eyeSquintRight eyeWideLeft
eyeWideRight jawForward jawLeft jawOpen jawRight mouthClose mouthDimpleLeft mouthDimpleRight mouthFrownLeft
mouthFrownRight mouthFunnel mouthLeft mouthLowerDownLeft mouthLowerDownRight mouthPressLeft mouthPressRight mouthPucker
mouthRight mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper mouthSmileLeft mouthSmileRight
mouthStretchLeft mouthStretchRight mouthUpperUpLeft mouthUpperUpRight noseSneerLeft noseSneerRight""".split()
PYFEAT_FEAT_EMOTION_COLUMNS = ["anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral"]
PYFEAT_EXPECTED = {"blendshapes": PYFEAT_MP_BLENDSHAPE_NAMES, "emotions": PYFEAT_FEAT_EMOTION_COLUMNS}


def pyfeat_predict(z, x: np.ndarray) -> np.ndarray:
    """py-feat's loader + ``PLSFeatMeshModel.predict``, transcribed: (n, 1434)."""
    feature_columns = [str(s) for s in z["feature_columns"]]
    coef = np.asarray(z["coef"], dtype=np.float32)
    intercept = np.asarray(z["intercept"], dtype=np.float32)
    k = len(feature_columns)
    return np.asarray(x, np.float32).reshape(-1, k) @ coef[:k] + intercept


def design(x: np.ndarray, pose: np.ndarray, columns: list[str], inputs: tuple[str, ...]) -> np.ndarray:
    """The design matrix ``[inputs | pose | pose-major pose x input]`` in ``columns`` order, built by name."""
    named = {n: x[:, j] for j, n in enumerate(inputs)}
    for p, name in enumerate(("Pitch", "Yaw", "Roll")):
        named[name] = pose[:, p]
        for j, n in enumerate(inputs):
            named[f"{name}*{n}"] = pose[:, p] * x[:, j]
    return np.column_stack([named[c] for c in columns])


def family_fit(family: str, n: int = 600, seed: int = 0, zero: tuple[str, ...] = ()):
    """A family fit as ``build/families/<family>/model.npz`` holds it, on synthetic meshes with a known field per
    input, in image pixels (y down: the frame prepare aligns to); ``zero`` inputs are 0 in every frame."""
    rng = seeded_rng(seed)
    reference = face_reference(rng)
    template = reference["mean_low_au_mesh"]
    au_fields = rng.normal(scale=2.0, size=(20, N_TARGETS))
    fields = family_fields(au_fields, template)[family]
    blend, emo = draw_family_values(rng, n)
    x = blend if family == "blendshapes" else emo
    inputs = FAMILIES[family]
    for name in zero:
        x[:, inputs.index(name)] = 0.0
    pose = rng.normal(scale=5.0, size=(n, 3))
    columns = feature_set_columns(f"{family}_pose_interactions")
    xd = design(x, pose, columns, inputs)
    y = flatten_axis_major(template)[None] + x @ fields + rng.normal(scale=0.05, size=(n, N_TARGETS))
    y += pose @ rng.normal(scale=0.3, size=(3, N_TARGETS))
    pls = PLSRegression(n_components=min(12, len(columns)), scale=False).fit(xd, y)
    model = {
        "coef": np.asarray(pls.coef_, dtype=np.float64),  # (1434, p), sklearn's layout
        "mesh_intercept": pls.raw_intercept_for(pls.n_components),  # the intercept for raw inputs, as evaluate saves
        "feature_columns": np.array(columns),
        "n_components": np.array(pls.n_components),
        "family": np.array(family),
    }
    return model, reference, x, pose, xd, pls


def release(family: str, **kw):
    model, reference, x, pose, xd, pls = family_fit(family, **kw)
    arrays = family_release.family_release_arrays(
        family,
        model["coef"],
        model["mesh_intercept"],
        model["feature_columns"].tolist(),
        int(model["n_components"]),
        reference,
        family_release.ranges_of(x, FAMILIES[family]),
        card_text="card",
        metadata={"family": family},
    )
    return arrays, model, reference, x, pose, xd, pls


@pytest.fixture(scope="module", params=["blendshapes", "emotions"])
def made(request):
    return request.param, *release(request.param)


def test_npz_keys_shapes_dtypes(made, tmp_path):
    family, arrays, model, *_ = made
    k, p = len(FAMILIES[family]), len(model["feature_columns"])
    path = tmp_path / family_release.npz_name(family)
    np.savez(path, **arrays)
    with np.load(path, allow_pickle=False) as z:  # py-feat's loader: no pickle
        assert z["coef"].shape == (p, N_TARGETS) and z["coef"].dtype == np.float32
        assert z["intercept"].shape == (N_TARGETS,) and z["intercept"].dtype == np.float32
        assert [str(s) for s in z["feature_columns"]] == PYFEAT_EXPECTED[family]
        assert [str(s) for s in z["pose_columns"]] == ["Pitch", "Yaw", "Roll"]
        for key in ("mean_aligned_mesh", "mean_neutral_mesh"):
            assert z[key].shape == (478, 3) and z[key].dtype == np.float32
        assert z["feature_p99"].shape == (k,) and z["feature_p99"].dtype == np.float32
        assert z["unsupported_features"].ndim == 1 and z["unsupported_features"].dtype.kind == "U"
        assert [str(s) for s in z["input_columns"][:k]] == PYFEAT_EXPECTED[family]
        assert int(z["n_components"]) == int(model["n_components"])
        assert str(z["family"]) == family and str(z["model_card"]) == "card"
    assert path.name == {"blendshapes": "bs_to_mesh_pls.npz", "emotions": "emotion_to_mesh_pls.npz"}[family]


def test_feature_columns_are_pyfeats_lists():
    # aumesh's lists against py-feat's, copied as text above: the loader raises "feature_columns drifted" otherwise
    assert list(BLENDSHAPE_COLUMNS) == PYFEAT_MP_BLENDSHAPE_NAMES
    assert list(EMOTION_COLUMNS) == PYFEAT_FEAT_EMOTION_COLUMNS


PYFEAT_UTILS = Path("/tmp/pyfeat/src/feat/utils/__init__.py")  # py-feat 2.1.5's source, where it is unpacked


@pytest.mark.skipif(not PYFEAT_UTILS.is_file(), reason="py-feat 2.1.5's source is not unpacked at /tmp/pyfeat")
def test_feature_columns_are_pyfeats_source_lists():
    # the same lists read from py-feat's own source (its module-level literals), not from a copy
    import ast

    found = {}
    for node in ast.parse(PYFEAT_UTILS.read_text()).body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            if node.targets[0].id in ("MP_BLENDSHAPE_NAMES", "FEAT_EMOTION_COLUMNS"):
                found[node.targets[0].id] = ast.literal_eval(node.value)
    assert found["MP_BLENDSHAPE_NAMES"] == list(BLENDSHAPE_COLUMNS)
    assert found["FEAT_EMOTION_COLUMNS"] == list(EMOTION_COLUMNS)


def test_round_trip_pyfeat_predict_is_the_fit_at_pose_0(made):
    family, arrays, model, reference, x, pose, xd, pls = made
    # the fit's own prediction at pose 0 (pose and pose x input columns 0), turned into the card frame
    xd0 = design(x[:50], np.zeros((50, 3)), model["feature_columns"].tolist(), FAMILIES[family])
    rotation, origin = canonical_frame(reference["mean_aligned_mesh"])
    expected = rotate_axis_major(pls.predict(xd0), rotation, origin)
    got = pyfeat_predict(arrays, x[:50])
    scale = np.abs(expected).max()
    assert np.abs(got - expected).max() < 1e-5 * scale


def test_rows_are_picked_by_name_not_position(made):
    family, arrays, model, reference, x, *_ = made
    # the same fit with its design columns shuffled gives the same NPZ
    perm = seeded_rng(5).permutation(len(model["feature_columns"]))
    shuffled = family_release.family_release_arrays(
        family,
        model["coef"][:, perm],
        model["mesh_intercept"],
        model["feature_columns"][perm].tolist(),
        int(model["n_components"]),
        reference,
        family_release.ranges_of(x, FAMILIES[family]),
    )
    np.testing.assert_array_equal(shuffled["coef"], arrays["coef"])
    np.testing.assert_array_equal(shuffled["input_columns"], arrays["input_columns"])


def test_frame_is_upright_as_pyfeat_draws_it(made):
    # plot_face_mesh: "+Y up (forehead at ~+8, chin at ~-8), +Z out of the face"; x toward the subject's left
    _, arrays, *_ = made
    k = len(arrays["feature_columns"])
    face = pyfeat_predict(arrays, np.zeros(k)).reshape(3, 478).T
    assert face[10, 1] > face[152, 1]  # forehead above chin
    assert face[263, 0] > face[33, 0]  # the subject's left eye at larger x
    assert face[1, 2] > face[[33, 263], 2].mean()  # nose tip in front of the eyes


def test_p99_and_unsupported_from_the_training_inputs():
    arrays, _, _, x, *_ = release("blendshapes", zero=("cheekPuff", "jawForward"))
    np.testing.assert_allclose(arrays["feature_p99"], np.quantile(x, 0.99, axis=0).astype(np.float32), rtol=1e-6)
    # an input constant at 0 has p99 0 < 0.05: never expressed; the beta(0.6, 3) draws have p99 ~0.75
    assert arrays["unsupported_features"].tolist() == ["cheekPuff", "jawForward"]
    assert support.UNSUPPORTED_P99 == 0.05


def test_unsupported_none_when_all_expressed():
    arrays, *_ = release("emotions")
    assert arrays["unsupported_features"].shape == (0,)


def test_not_a_family_fit_is_one_line():
    model, reference, x, *_ = family_fit("emotions")
    with pytest.raises(ValueError, match=r"lack \['_neutral'.*not a blendshapes fit"):
        family_release.design_rows(model["coef"], model["feature_columns"].tolist(), "blendshapes")
    with pytest.raises(ValueError, match="has no family release"):
        family_release.npz_name("au")
