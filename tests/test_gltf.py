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
from conftest import REPO, upright_truth_release

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
