"""A clip as an animated glTF 2.0 file: the release's blendshape rig (:mod:`aumesh.export.gltf`, the same base mesh,
20 AU morph targets, triangles and material as ``release/au_to_mesh.glb``) plus one animation.

* **family** (issue 46): with a blendshape or emotion release (``aumesh animate --family blendshapes``) the rig is that
  release's (:func:`aumesh.export.gltf.rig_arrays`: one morph target per input, named by the family: MediaPipe's 52
  ARKit-style names, py-feat's 7 emotions) and the weights are the clip's columns of that family, read by name
  (:func:`aumesh.core.families.family_columns`: Detectorv2's ``Happy`` drives ``happiness``); the rest as for AUs.
* **weights**: a LINEAR sampler on the mesh's morph ``weights``, one keyframe per frame of the clip (py-feat's rows:
  ``skip_frames`` leaves longer steps, which the player interpolates linearly), the frame's AU intensities; no-face
  frames bridged by :func:`aumesh.data.clip.bridge` (interpolated in a gap up to ``max_gap_s``, held in a longer
  one). Sampled at a keyframe, the rig is ``base + sum_k w_k target_k``: the frame's ``predict_mesh`` at pose 0.
* **time**: keyframe ``i`` at ``time[i] - time[0]`` seconds (float32): the animation starts at 0 at the clip's first
  row, whatever its frame number; ``asset.extras`` records the first frame and its time in the video.
* **pose** (``pose=True``): a LINEAR ``rotation`` sampler on a parent node ("head") holding the quaternion (``x, y,
  z, w``) of ``Rotation.from_euler("xyz", [Pitch, Yaw, Roll])``, the card's render-time rotation
  (``posed = canonical @ R.T``), about the neutral face's centre (the mean of the base mesh's vertices, as the
  viewer turns it). Consecutive quaternions are kept in one hemisphere so the player's slerp takes the short way.
* **smoothing** (``smooth_frames`` N, odd): a centred moving average over N frames of the bridged weights (and pose),
  for detector jitter.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.data.clip import MAX_GAP_S, Clip, bridged_pose, bridged_weights, read_clip, smooth
from aumesh.export import gltf

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClipSummary:
    """What :func:`write_clip_glb` wrote: frames, seconds, frame rate and its source, gaps bridged and held."""

    path: Path
    frames: int
    face_frames: int
    duration: float
    fps: float
    fps_source: str
    gaps_bridged: int
    gaps_held: int
    bytes: int

    def line(self) -> str:
        """One line for the command: what was written."""
        no_face = self.frames - self.face_frames
        gaps = (
            f"{no_face} no-face frame(s): {self.gaps_bridged} gap(s) interpolated, {self.gaps_held} held"
            if no_face
            else "no gaps"
        )
        return (
            f"wrote {self.path} ({self.frames} frames, {self.duration:.2f} s at {self.fps:g} fps from "
            f"{self.fps_source}; {gaps}; {self.bytes / 1e6:.1f} MB)"
        )


def pose_quaternions(pose: np.ndarray) -> np.ndarray:
    """(n, 4) glTF rotations ``x, y, z, w`` of Pitch, Yaw, Roll (n, 3) radians: ``Rotation.from_euler("xyz", ...)``,
    signs chosen so consecutive quaternions are less than 180 degrees apart along the slerp."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("xyz", np.asarray(pose, np.float64)).as_quat()  # scalar last, glTF's order
    flip = np.r_[False, np.einsum("ij,ij->i", q[1:], q[:-1]) < 0]
    sign = np.where(np.logical_xor.accumulate(flip), -1.0, 1.0)  # each flip turns every later quaternion over
    return q * sign[:, None]


def clip_animation(
    clip: Clip,
    npz: Mapping[str, Any],
    *,
    pose: bool = False,
    smooth_frames: int = 1,
    max_gap_s: float = MAX_GAP_S,
) -> gltf.Animation:
    """The clip's keyframes for the rig of release ``npz`` (module docstring)."""
    weights = smooth(bridged_weights(clip, max_gap_s), smooth_frames)
    rotations = pivot = None
    if pose:
        rotations = pose_quaternions(smooth(bridged_pose(clip, max_gap_s), smooth_frames))
        pivot = gltf.rig_arrays(npz)["base"].astype(np.float64).mean(axis=0)
    return gltf.Animation(
        times=clip.time - clip.time[0], weights=weights, rotations=rotations, pivot=pivot, name=clip.video
    )


def clip_glb_bytes(
    npz: Mapping[str, Any],
    clip: Clip,
    *,
    pose: bool = False,
    smooth_frames: int = 1,
    max_gap_s: float = MAX_GAP_S,
    release: str | None = None,
) -> bytes:
    """The animated GLB's bytes (module docstring); ``release`` (the NPZ's name) goes in ``asset.extras``."""
    animation = clip_animation(clip, npz, pose=pose, smooth_frames=smooth_frames, max_gap_s=max_gap_s)
    bridged, held = clip.gaps(max_gap_s)
    extras = {
        "inputs": gltf.inputs_note(npz)
        + " over time; mesh at pose 0"
        + ("; node 'head' rotation = Rotation.from_euler('xyz', [Pitch, Yaw, Roll])" if pose else ""),
        "units_and_frame": "the release NPZ's (see its model card)",
        "release": release,
        "table": clip.source,
        "video": clip.video,
        "fps": clip.fps,
        "fps_source": clip.fps_source,
        "first_frame": int(clip.frame[0]),
        "first_frame_time_s": float(clip.time[0]),
        "frames": len(clip),
        "face_frames": int(clip.has_face.sum()),
        "gap_rule": f"no-face frames: linear interpolation between the neighbouring face frames when they are at most "
        f"{max_gap_s:g} s apart, else the last face frame held ({bridged} gap(s) interpolated, {held} held)",
        "smooth_frames": smooth_frames,
        **gltf.family_extras(npz),
    }
    return gltf.glb_bytes(npz, name=f"aumesh clip {clip.video}", extras=extras, animation=animation)


def write_clip_glb(
    npz: Mapping[str, Any],
    clip: Clip,
    path: str | Path,
    *,
    pose: bool = False,
    smooth_frames: int = 1,
    max_gap_s: float = MAX_GAP_S,
    release: str | None = None,
) -> ClipSummary:
    """Write the clip's animated GLB to ``path`` atomically (never half-written); what was written."""
    from aumesh.core.io import atomic_path

    data = clip_glb_bytes(npz, clip, pose=pose, smooth_frames=smooth_frames, max_gap_s=max_gap_s, release=release)
    with atomic_path(path, suffix=".glb") as tmp:
        tmp.write_bytes(data)
    bridged, held = clip.gaps(max_gap_s)
    return ClipSummary(
        Path(path),
        len(clip),
        int(clip.has_face.sum()),
        clip.duration,
        clip.fps,
        clip.fps_source,
        bridged,
        held,
        len(data),
    )


def check_clip_inputs(npz: Mapping[str, Any], clip: Clip, *, pose: bool = False, where: str = "table") -> None:
    """Log, once for the clip, what :func:`aumesh.predict_mesh` warns of its face frames (AUs beyond the training
    data, unsupported AUs given, with ``pose`` a pose beyond the training range: one line) and a table from another
    detector than the release's (:func:`aumesh.model.support.detector_mismatch`, from the table's layout)."""
    import warnings

    from aumesh.model import support
    from aumesh.model.input_checks import InputRangeWarning, input_rows, logged_range_warnings

    face = clip.has_face
    if clip.inputs is not None:  # a family's clip (issue 46): the family release's checks, by its own names
        from aumesh.model.family_inference import family_input_rows

        with logged_range_warnings(log, where):
            family_input_rows(npz, clip.inputs[face], clip.pose[face] if pose else None)
        return
    with logged_range_warnings(log, where):
        mismatch = support.detector_mismatch(clip.detector, support.release_support(npz), "table")
        if mismatch:
            warnings.warn(mismatch, InputRangeWarning, stacklevel=1)
        input_rows(npz, clip.aus[face], clip.pose[face] if pose else None)


def animate(
    table: str | Path,
    release: str | Path,
    out: str | Path,
    *,
    video: str | None = None,
    fps: float | None = None,
    pose: bool = False,
    smooth_frames: int = 1,
    max_gap_s: float = MAX_GAP_S,
    family: str | None = None,
) -> ClipSummary:
    """``aumesh animate``: read one video of a py-feat table (:func:`~aumesh.data.clip.read_clip`), write its
    animated GLB with release ``release``'s rig to ``out``.

    ``family`` (``--family``): ``au``, ``blendshapes`` or ``emotions``, which must be the release's (a one-line error
    naming both otherwise); None: the release's own. A family's columns are read from the table by name; a column
    the table lacks is one line naming the file, the column and the fix."""
    from aumesh.core.errors import UserError
    from aumesh.model.family_inference import load_any_release, release_family

    out = Path(out)
    if out.suffix.lower() != ".glb":
        raise UserError(f"--out {out}: write a .glb (binary glTF 2.0) file, e.g. --out clip.glb.")
    smooth(np.zeros((1, 1)), smooth_frames)  # an even --smooth is refused before the table is read
    npz = load_any_release(release)
    found = release_family(npz)
    if family is not None and family != found:
        raise UserError(
            f"--release {release} is {'an AU' if found == 'au' else f'the {found}'} release, not the {family} "
            f"release --family {family} needs. Fix: pass --release {default_release(family)} (or drop --family)."
        )
    # the recorded mesh is not animated
    clip = read_clip(table, video=video, fps=fps, mesh_units=None, family=found)
    check_clip_inputs(npz, clip, pose=pose, where=str(table))
    return write_clip_glb(
        npz, clip, out, pose=pose, smooth_frames=smooth_frames, max_gap_s=max_gap_s, release=Path(release).name
    )


def default_release(family: str | None) -> Path:
    """``release/au_to_mesh_pls.npz`` for the AUs (and None), ``releases/<family>/<py-feat stem>.npz`` for a family
    (contract item 3: ``releases/blendshapes/bs_to_mesh_pls.npz``, ``releases/emotions/emotion_to_mesh_pls.npz``)."""
    from aumesh.core.families import PYFEAT_FEATURE, check_family

    if family is None or family == "au":
        return Path("release/au_to_mesh_pls.npz")
    check_family(family)
    return Path("releases") / family / f"{PYFEAT_FEATURE[family][1]}.npz"


__all__ = [
    "default_release",
    "ClipSummary",
    "animate",
    "check_clip_inputs",
    "clip_animation",
    "clip_glb_bytes",
    "pose_quaternions",
    "write_clip_glb",
]
