"""``aumesh synth --families`` (issue 46): the demo tables with the 52 blendshapes and 7 emotions, each with a known
field on the mesh, and without the flag the tables and truth byte for byte as the generator wrote them before."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from aumesh.core.schema import AU_COLUMNS, N_VERTICES, POSE_COLUMNS
from aumesh.synthetic import tables as synth
from aumesh.synthetic.family_truth import family_source
from conftest import REPO

#: The i46 commit before the families' option: its generator is the reference for "unchanged without the flag".
BEFORE_FAMILIES = "ddb088c"
KWARGS = dict(n_frames=240, n_videos=8, seed=4, frames_per_file=120)
# py-feat 2.1.5's FEAT_EMOTION_COLUMNS and the first/last of MP_BLENDSHAPE_NAMES, as written there
EMOTIONS = ["anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral"]


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(f.relative_to(folder)): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(folder.rglob("*"))
        if f.is_file()
    }


def _old_tables_module() -> types.ModuleType:
    """``aumesh.synthetic.tables`` as it was at :data:`BEFORE_FAMILIES` (skipped without the git history)."""
    try:
        source = subprocess.run(
            ["git", "show", f"{BEFORE_FAMILIES}:src/aumesh/synthetic/tables.py"],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip(f"git history with {BEFORE_FAMILIES} not available")
    module = types.ModuleType("old_synth_tables_families")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    try:
        exec(compile(source, "old_synth_tables_families", "exec"), module.__dict__)  # noqa: S102 - our own file, older
    finally:
        del sys.modules[module.__name__]
    return module


@pytest.mark.parametrize("layout", ["columns", "pyfeat"])
def test_without_the_flag_the_tables_and_truth_are_byte_identical_to_before(tmp_path, layout):
    old = _old_tables_module()
    old.write_tables(tmp_path / "old", old.SynthSpec(layout=layout, **KWARGS), tmp_path / "old" / "truth.npz")
    synth.write_tables(tmp_path / "new", synth.SynthSpec(layout=layout, **KWARGS), tmp_path / "new" / "truth.npz")
    old_files, new_files = _digests(tmp_path / "old"), _digests(tmp_path / "new")
    assert len(old_files) >= 3 and new_files == old_files


def _mesh(df: pd.DataFrame) -> np.ndarray:
    """(n, 478, 3) the interleaved mesh columns of a ``columns`` table, float64."""
    cols = [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]
    return df[cols].to_numpy(np.float64).reshape(len(df), N_VERTICES, 3)


def test_the_families_are_written_with_a_known_field_on_the_mesh(tmp_path):
    spec = synth.SynthSpec(**KWARGS)
    synth.write_tables(tmp_path / "plain", spec)
    synth.write_tables(tmp_path / "fam", spec, tmp_path / "truth.npz", families=family_source(spec))
    plain = pd.concat([pd.read_parquet(f) for f in sorted((tmp_path / "plain").glob("*.parquet"))], ignore_index=True)
    fam = pd.concat([pd.read_parquet(f) for f in sorted((tmp_path / "fam").glob("*.parquet"))], ignore_index=True)
    truth = np.load(tmp_path / "truth.npz")
    blend_names, emo_names = list(truth["blendshape_columns"]), list(truth["emotion_columns"])
    assert emo_names == EMOTIONS and len(blend_names) == 52 and blend_names[0] == "_neutral"
    assert blend_names[-1] == "noseSneerRight" and blend_names[25] == "jawOpen"
    # as py-feat writes them: blendshapes in [0, 1], emotions a softmax (each in [0, 1], summing to 1)
    blend, emo = fam[blend_names].to_numpy(), fam[emo_names].to_numpy()
    assert blend.min() >= 0 and blend.max() <= 1 and emo.min() >= 0 and emo.max() <= 1
    np.testing.assert_allclose(emo.sum(axis=1), 1.0, atol=1e-12)
    assert blend.std(axis=0).min() > 0.01 and emo.std(axis=0).min() > 0.01  # every input moves
    # everything else as without the flag: the same frames, AUs and pose (no draw of another stream changed)
    same = ["video_id", "frame", "input", "FaceScore", *AU_COLUMNS, *POSE_COLUMNS]
    pd.testing.assert_frame_equal(fam[same], plain[same])
    assert list(fam.columns) == [*plain.columns[: plain.columns.get_loc("Yaw") + 1], *blend_names, *emo_names,
                                 *plain.columns[plain.columns.get_loc("Yaw") + 1 :]]  # fmt: skip
    # the mesh moved by the families' fields from the truth file: observed = s R (canonical - its centre) + shift +
    # noise with the same draws, so the difference is s R (e - mean e), e = blend @ fields + emo @ fields (canonical
    # frame, pixels), R the recorded pose (the generator's convention), s the frame's scale (solved here)
    e = (blend @ truth["blendshape_fields"] + emo @ truth["emotion_fields"]).reshape(len(fam), 3, N_VERTICES)
    e = e.transpose(0, 2, 1)
    e -= e.mean(axis=1, keepdims=True)
    rot = Rotation.from_euler("xyz", fam[list(POSE_COLUMNS)].to_numpy()).as_matrix()
    expected = np.einsum("fvj,fij->fvi", e, rot)
    diff = _mesh(fam) - _mesh(plain)
    scale = (diff * expected).sum(axis=(1, 2)) / (expected**2).sum(axis=(1, 2))
    residual = diff - scale[:, None, None] * expected
    assert np.all((scale > 0.6) & (scale < 1.6))  # the generator's uniform(0.7, 1.5) x exp(N(0, 0.02))
    assert np.sqrt((residual**2).mean()) < 1e-3 * np.sqrt((diff**2).mean())  # float32 rounding only
