"""The glTF blendshape rig is the model at pose 0 and passes the Khronos glTF-Validator."""

from __future__ import annotations

import json
import struct
import subprocess

import numpy as np
import pytest

from aumesh.core.schema import AU_COLUMNS
from aumesh.export import gltf
from aumesh.model.release import load_npz
from conftest import REPO, identification_keys, upright_truth_release

COMPONENT = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def parse_glb(path):
    """GLB 2.0 by its spec (header, JSON chunk, BIN chunk): no pygltflib, no aumesh code."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON"
    doc = json.loads(data[20 : 20 + json_len])
    bin_len, bin_type = struct.unpack_from("<I4s", data, 20 + json_len)
    assert bin_type == b"BIN\0"
    blob = data[28 + json_len : 28 + json_len + bin_len]

    def accessor(i):
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        n = acc["count"] * WIDTH[acc["type"]]
        arr = np.frombuffer(
            blob, COMPONENT[acc["componentType"]], n, view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        )
        return arr.reshape(acc["count"], -1) if WIDTH[acc["type"]] > 1 else arr

    return doc, accessor


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("rig")
    npz = upright_truth_release(d / "release.npz")
    return npz, gltf.write_glb(load_npz(npz), d / gltf.GLB_NAME, source=npz.name)


def test_rig_is_the_model_at_pose_zero(rig):
    npz_path, glb = rig
    doc, accessor = parse_glb(glb)
    mesh = doc["meshes"][0]
    prim = mesh["primitives"][0]
    assert mesh["extras"]["targetNames"] == list(AU_COLUMNS)
    assert len(prim["targets"]) == 20 and mesh["weights"] == [0.0] * 20
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    targets = np.stack([accessor(t["POSITION"]) for t in prim["targets"]]).astype(np.float64)
    m = np.load(npz_path, allow_pickle=False)
    rng = np.random.default_rng(0)
    for w in [np.zeros(20), np.eye(20)[AU_COLUMNS.index("AU12")] * 2.5, rng.uniform(0, 5, 20)]:
        x = np.concatenate([w, np.zeros(3)])  # the card's snippet at pose 0
        flat = x @ m["coef"].astype(np.float64) + m["intercept"].astype(np.float64)
        expected = np.stack([flat[:478], flat[478:956], flat[956:]], axis=1)
        rig_mesh = base + np.tensordot(w, targets, axes=1)
        np.testing.assert_allclose(
            rig_mesh, expected, rtol=0, atol=4 * np.finfo(np.float32).eps * np.abs(expected).max()
        )
    # POSITION bounds are required by the spec and must be the data's
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_array_equal(acc["min"], base.min(axis=0).astype(np.float32))


def test_triangles_and_normals_face_out_of_the_face(rig):
    _, glb = rig
    doc, accessor = parse_glb(glb)
    prim = doc["meshes"][0]["primitives"][0]
    assert prim.get("mode", 4) == 4
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    normals = accessor(prim["attributes"]["NORMAL"]).astype(np.float64)
    tri = accessor(prim["indices"]).reshape(-1, 3)
    assert len(tri) > 400 and tri.max() < 478
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    # the fixture is y up, z out of the face: fronts (counter-clockwise, glTF) and normals point to +z
    face_n = np.cross(base[tri[:, 1]] - base[tri[:, 0]], base[tri[:, 2]] - base[tri[:, 0]])
    assert np.mean(face_n[:, 2] > 0) > 0.95
    assert normals[1, 2] > 0.5 and normals[151, 2] > 0.9  # nose tip and forehead look forward
    assert np.mean(normals[:, 2] > 0) > 0.9


def test_rig_passes_the_khronos_gltf_validator(rig, node_tools):
    _, glb = rig
    proc = subprocess.run(
        ["node", str(REPO / "tests" / "tools" / "validate_gltf.cjs"), str(glb)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    report = json.loads(proc.stdout)
    issues = report["issues"]
    assert issues["numErrors"] == 0, issues["messages"]
    assert issues["numWarnings"] == 0, issues["messages"]
    assert report["info"]["hasMorphTargets"] and report["info"]["totalVertexCount"] == 478


# ---------------------------------------------------------------- issue 43: the identification screen in extras
@pytest.fixture(scope="module")
def flagged_rig(tmp_path_factory):
    """The same release with the screen's keys (AU10 behind AU09, AU02 behind AU01 flagged), as a rig."""
    d = tmp_path_factory.mktemp("flagged_rig")
    arrays = {**load_npz(upright_truth_release(d / "release.npz")), **FLAGGED_KEYS}
    return gltf.write_glb(arrays, d / gltf.GLB_NAME, source="release.npz")


FLAGGED_KEYS = identification_keys({"AU02": (0.08, "AU01"), "AU10": (0.06, "AU09")})


def test_rig_extras_carry_the_identification_screen(rig, flagged_rig):
    """Read back by the spec's own parser: per AU sigma* (NaN as null), flag, partner and group, the threshold, the
    flagged targets on the mesh; the geometry is the unflagged rig's, byte for byte; an old release has none of it."""
    doc, _ = parse_glb(flagged_rig)
    ident = doc["asset"]["extras"]["au_identification"]
    assert ident["flag_below"] == 0.1 and ident["flagged"] == ["AU02", "AU10"]
    assert ident["groups"] == {"AU01+AU02": ["AU01", "AU02"], "AU09+AU10": ["AU09", "AU10"]}
    assert list(ident["aus"]) == list(AU_COLUMNS)
    assert ident["aus"]["AU10"] == {"sigma_star": 0.06, "flagged": True, "partner": "AU09", "group": "AU09+AU10"}
    sigma = FLAGGED_KEYS["au_identification_sigma_star"]
    for k, au in enumerate(AU_COLUMNS):
        got = ident["aus"][au]
        assert got["sigma_star"] == (None if np.isnan(sigma[k]) else sigma[k]), au
        assert got["flagged"] == bool(FLAGGED_KEYS["au_identification_flagged"][k])
        assert got["partner"] == str(FLAGGED_KEYS["au_identification_partner"][k])
    assert "a screen, not a proof" in ident["note"].lower()
    assert doc["meshes"][0]["extras"] == {"targetNames": list(AU_COLUMNS), "unidentifiedTargets": ["AU02", "AU10"]}
    assert doc["asset"]["extras"]["source"] == "release.npz"  # the other extras kept
    _, old = rig
    old_doc, _ = parse_glb(old)
    assert (
        "au_identification" not in old_doc["asset"]["extras"]
        and "unidentifiedTargets" not in old_doc["meshes"][0]["extras"]
    )
    blob = lambda path: path.read_bytes()[28 + struct.unpack_from("<I", path.read_bytes(), 12)[0] :]  # noqa: E731
    assert blob(flagged_rig) == blob(old)


def test_flagged_rig_passes_the_khronos_gltf_validator(flagged_rig, node_tools):
    proc = subprocess.run(
        ["node", str(REPO / "tests" / "tools" / "validate_gltf.cjs"), str(flagged_rig)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    issues = json.loads(proc.stdout)["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def test_a_screen_that_flags_nothing_says_so_in_the_extras(tmp_path):
    """Nothing flagged: the lists are written empty and every sigma* null (pygltflib alone would drop them all)."""
    arrays = {**load_npz(upright_truth_release(tmp_path / "release.npz")), **identification_keys({})}
    doc, _ = parse_glb(gltf.write_glb(arrays, tmp_path / gltf.GLB_NAME))
    ident = doc["asset"]["extras"]["au_identification"]
    assert ident["flagged"] == [] and ident["groups"] == {} and doc["meshes"][0]["extras"]["unidentifiedTargets"] == []
    assert all(v["sigma_star"] is None and v["flagged"] is False for v in ident["aus"].values())
