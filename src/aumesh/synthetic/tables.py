"""Synthetic frame tables with a known ground truth, from demo size to CelebV-HQ scale and beyond.

The generator is honest about what makes the real problem hard:

* a known linear map  AU (+ pose, + pose x AU) -> canonical mesh, whose AU rows are
  FACS-plausible displacement fields on the project's face template (``aumesh.geometry.face``);
* per-video identity shape differences and per-frame expression variation the AUs do not
  explain, plus coordinate noise;
* random head rotation (the recorded Pitch, Yaw, Roll), scale and image-space translation,
  some frames outside the card's pose limits, and a few landmark failures;
* optionally (``profile_rate``), runs of frames with the head turned toward profile (|yaw| in
  ``profile_yaw_deg``), the mesh generated at that pose: the face's 2-D inter-ocular distance shrinks with
  cos(yaw), its height does not. Off by default, and then no random draw changes: every table is as before;
* optionally (``identity_au_coupling``), AU detectors that read a person's resting face as some
  expression: each video's recorded AUs start from a baseline that rises with how much the person's
  identity shape resembles the AU's field (a naturally upturned mouth corner reads as AU12). The mesh
  follows the true AUs; the table records ``baseline + (1 - baseline) * true`` (still in [0, 1]).
  Pooled (card) regression then leaks identity into the AU fields; within-video regression does not;
* optionally (``au_coactivation``), AUs that co-activate more tightly than through the shared expressions: in each
  pair of ``coactivated_aus`` the follower follows the leader (``b <- (1 - c) b + c a``; AU09/AU10 at c = 0.6 have a
  within-video correlation of ~0.88, like the issue's py-feat tables), and ``au_activity`` scales the AUs'
  within-video variation;
* optionally (``au_noise_sd``), detector noise on the recorded AUs (the mesh follows the true AUs): a stationary
  AR(1) error in time, correlated across the AU pairs py-feat's detectors read together
  (:mod:`aumesh.synthetic.au_noise`); its within-video covariance is :func:`au_noise.au_error_covariance`, written
  to the truth file. ``instrument_noise_sd``: a second detector's AUs on the same frames (``AU01_2`` ...), with its
  own independent error. Off by default, and then no random draw changes.

Frames are generated and written video by video, file by file, so memory stays bounded at
any size. Layouts: ``columns`` (mesh columns ``x_i, y_i, z_i`` interleaved, pose stored in
Fex order Pitch, Roll, Yaw) or ``pyfeat`` (AU/pose parquet + ``[N, 478, 3]`` float16 .npy).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.spatial.transform import Rotation

from aumesh.core.io import atomic_path, atomic_savez
from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, N_VERTICES, POSE_COLUMNS, feature_columns, flatten_axis_major
from aumesh.synthetic import au_noise

#: AU pairs that co-activate (``SynthSpec.au_coactivation``): ``(leader, follower, weight)``, the follower follows the
#: leader with strength ``au_coactivation * weight``. FACS's frequent combinations, which py-feat's detectors also read
#: together (:data:`au_noise.DETECTOR_PAIRS`): nose wrinkle with upper-lip raise (disgust), cheek raise with lip-corner
#: pull (Duchenne smile), brow raises, lips part with jaw drop; and in speech lips parting and pressing with the same
#: talk activity (AU24's field opposes AU25's, which is 1.7x larger: the pair a detector's noise can reverse).
COACTIVATED_AUS: tuple[tuple[str, str, float], ...] = (
    ("AU09", "AU10", 0.6),
    ("AU06", "AU12", 0.6),
    ("AU01", "AU02", 0.6),
    ("AU25", "AU26", 0.2),
    ("AU25", "AU24", 0.7),
)


@dataclass(frozen=True)
class SynthSpec:
    """Size and difficulty of a synthetic set. Lengths are in inter-ocular units (IOD) unless ``_px``."""

    n_frames: int = 4000
    n_videos: int = 100
    seed: int = 0
    px_per_iod: float = 60.0  # canonical face size in pixels
    identity_scale: float = 0.005  # per-video shape differences
    unexplained_scale: float = 0.006  # per-frame expression the AUs do not capture
    noise_px: float = 0.25  # landmark jitter per coordinate
    pose_effect: float = 0.03  # non-rigid pose-correlated deformation per radian
    interaction_gain: tuple[float, float, float] = (0.3, -0.25, 0.15)  # AU effect change per radian of Pitch, Yaw, Roll
    yaw_sd_deg: float = 18.0
    pitch_sd_deg: float = 10.0
    roll_sd_deg: float = 7.0
    landmark_failure_rate: float = 0.003
    frames_per_file: int = 25000
    layout: str = "columns"  # or "pyfeat"
    reversed_aus: tuple[str, ...] = ()  # truth deliberately reversed (tests of the AU-direction check)
    # AU baseline per unit softplus of the identity's standardized resemblance to the AU field (0 = off)
    identity_au_coupling: float = 0.0
    # fraction of each video's frames (in runs of PROFILE_RUN frames) turned toward profile (0 = off: no draw)
    profile_rate: float = 0.0
    profile_yaw_deg: tuple[float, float] = (60.0, 85.0)  # |yaw| of those frames
    # how tightly the pairs of coactivated_aus co-activate: follower <- (1 - c) follower + c leader, c = this x the
    # pair's weight (0 = off)
    au_coactivation: float = 0.0
    coactivated_aus: tuple[tuple[str, str, float], ...] = COACTIVATED_AUS
    au_activity: float = 1.0  # the true AUs' within-video variation around each video's mean, scaled (1 = as drawn)
    # the AU detector's error on the recorded AUs (0 = off: no draw); AR(1) in time, correlated across AU pairs
    au_noise_sd: float = 0.0
    au_noise_ar: float = 0.7  # frame-to-frame AR(1) coefficient of the error (0.7: an error lasts several frames)
    au_noise_correlation: tuple[tuple[str, str, float], ...] = au_noise.DETECTOR_PAIRS  # (AU, AU, correlation)
    # a second detector's AUs on the same frames (columns "{au}_2"): the true AUs + its own independent error (0 = off)
    instrument_noise_sd: float = 0.0


#: Frames per run of profile frames (``SynthSpec.profile_rate``).
PROFILE_RUN = (5, 20)
#: SynthSpec fields added after the truth files' ``spec`` record was fixed: left out of it at their defaults, so
#: an unchanged spec writes the same truth file as before.
_LATER_FIELDS = {
    "profile_rate": 0.0,
    "profile_yaw_deg": (60.0, 85.0),
    "au_coactivation": 0.0,
    "coactivated_aus": COACTIVATED_AUS,
    "au_activity": 1.0,
    "au_noise_sd": 0.0,
    "au_noise_ar": 0.7,
    "au_noise_correlation": au_noise.DETECTOR_PAIRS,
    "instrument_noise_sd": 0.0,
}
#: Suffix of the second detector's AU columns (``instrument_noise_sd``): ``model.eiv.instrument_aus='{au}_2'``.
INSTRUMENT_SUFFIX = "_2"
INSTRUMENT_COLUMNS: tuple[str, ...] = tuple(au + INSTRUMENT_SUFFIX for au in AU_COLUMNS)


def _spec_record(spec: SynthSpec) -> dict:
    """``asdict(spec)`` without the later fields at their defaults (:data:`_LATER_FIELDS`)."""
    return {k: v for k, v in asdict(spec).items() if not (k in _LATER_FIELDS and v == _LATER_FIELDS[k])}


def profile_yaw(spec: SynthSpec, video: int, yaw: np.ndarray) -> np.ndarray:
    """``yaw`` (radians, (n,)) with runs of about ``spec.profile_rate`` of the frames turned toward profile: each run
    at one side's |yaw| drawn in ``spec.profile_yaw_deg``, 1 degree of jitter, kept inside that range. Its own random
    stream (seeded by the spec's seed and the video), drawn only when the rate is positive."""
    n = len(yaw)
    rng = np.random.default_rng([spec.seed, video, 7])
    target = int(np.floor(spec.profile_rate * n + rng.random()))
    out = yaw.copy()
    turned = np.zeros(n, dtype=bool)
    lo, hi = spec.profile_yaw_deg
    for _ in range(100 * (target + 1)):
        have = int(turned.sum())
        if have >= target:
            break
        length = min(int(rng.integers(PROFILE_RUN[0], PROFILE_RUN[1] + 1)), n, max(target - have, 1))
        start = int(rng.integers(0, n - length + 1))
        deg = rng.choice([-1.0, 1.0]) * np.clip(rng.uniform(lo, hi) + rng.normal(0, 1.0, length), lo, hi)
        out[start : start + length] = np.deg2rad(deg)
        turned[start : start + length] = True
    return out


def true_coefficients(spec: SynthSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The ground-truth linear map in the canonical template frame, in pixels.

    Returns
    -------
    coef : ndarray, shape (83, 1434)
        Rows ``[20 AU | 3 pose | 60 pose x AU]`` (``schema.feature_columns(True, True)``),
        columns axis-major ``[x_0..x_477 | y_.. | z_..]``.
    intercept : ndarray, shape (1434,)
        Template mesh in pixels (the canonical face at AU = 0, pose = 0, mean identity).
    columns : list of str
    """
    from aumesh.geometry import face
    from aumesh.synthetic import truth

    template = face.canonical_template()
    fields = np.array(truth.facs_displacement_fields(template), dtype=np.float64)  # (20, 478, 3)
    fields[:, list(ANCHOR_INDICES), :] = 0.0  # anchors stay rigid so alignment is not AU-driven
    for au in spec.reversed_aus:
        fields[AU_COLUMNS.index(au)] *= -1.0
    pose_fields = spec.pose_effect * _smooth_fields(template, 3, np.random.default_rng(10_000 + spec.seed))
    pose_fields[:, list(ANCHOR_INDICES), :] = 0.0
    gains = np.asarray(spec.interaction_gain)
    interaction = (gains[:, None, None, None] * fields[None]).reshape(60, N_VERTICES, 3)
    rows = np.concatenate([fields, pose_fields, interaction]) * spec.px_per_iod
    coef = flatten_axis_major(rows)
    intercept = flatten_axis_major(template[None] * spec.px_per_iod)[0]
    return coef, intercept, feature_columns(True, True)


def _smooth_fields(template: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` smooth random displacement fields, unit RMS, from quadratic polynomials of the template coordinates."""
    c = (template - template.mean(0)) / template.std(0).max()
    basis = np.column_stack(
        [np.ones(len(c)), c, c**2, c[:, [0]] * c[:, [1]], c[:, [1]] * c[:, [2]], c[:, [0]] * c[:, [2]]]
    )
    weights = rng.standard_normal((n, basis.shape[1], 3))
    out = np.einsum("vb,nbk->nvk", basis, weights)
    out -= out.mean(axis=1, keepdims=True)
    return out / np.sqrt((out**2).mean(axis=(1, 2), keepdims=True))


def _au_intensities(rng: np.random.Generator, n: int, propensity: np.ndarray) -> np.ndarray:
    """Correlated AU intensities in [0, 1], like py-feat's xgb AU outputs: a few expressions plus noise."""
    expressions = {  # AU sets that co-occur (smile, surprise, frown, talk, disgust)
        "smile": ("AU06", "AU12", "AU25"),
        "surprise": ("AU01", "AU02", "AU05", "AU26"),
        "frown": ("AU04", "AU07", "AU15", "AU17"),
        "talk": ("AU10", "AU25", "AU26", "AU20"),
        "disgust": ("AU09", "AU10", "AU11", "AU14"),
    }
    loading = np.zeros((len(expressions), len(AU_COLUMNS)))
    for k, aus in enumerate(expressions.values()):
        for au in aus:
            loading[k, AU_COLUMNS.index(au)] = 0.7
    latent = np.clip(rng.gamma(0.6, 0.35, size=(n, len(expressions))) * propensity[: len(expressions)], 0, 1.5)
    own = rng.beta(0.7, 3.0, size=(n, len(AU_COLUMNS))) * propensity[len(expressions) :]
    return np.clip(latent @ loading + own, 0.0, 1.0)


def _frames_per_video(spec: SynthSpec, rng: np.random.Generator) -> np.ndarray:
    if spec.n_videos < 1 or spec.n_frames < spec.n_videos:
        raise ValueError(
            f"synth: need n_frames >= n_videos >= 1, got n_frames={spec.n_frames}, n_videos={spec.n_videos}"
        )
    weights = rng.gamma(4.0, 1.0, size=spec.n_videos)
    counts = 1 + np.floor(weights / weights.sum() * (spec.n_frames - spec.n_videos)).astype(int)
    counts[: spec.n_frames - counts.sum()] += 1
    return counts


def frames_per_video(spec: SynthSpec) -> np.ndarray:
    """(n_videos,) frames of each video, as :func:`write_tables` splits ``spec.n_frames``."""
    return _frames_per_video(spec, np.random.default_rng(spec.seed))


#: The preset's correlated error pairs: :data:`au_noise.DETECTOR_PAIRS` without AU25/AU26. Measured
#: (benchmarks/au_noise_tables.py): with the AU25/AU26 errors correlated (even at 0.2) AU24's reversal is driven by that
#: correlation, and neither an isotropic screen nor a correction that knows only Sigma_u's diagonal sees it (the diagonal
#: correction leaves AU24 at -0.16 to -0.20); without it the reversal comes from co-activation, the issue's case. Pass
#: ``au_noise_correlation=au_noise.DETECTOR_PAIRS`` for the harder tables.
PRESET_NOISE_PAIRS: tuple[tuple[str, str, float], ...] = tuple(
    p for p in au_noise.DETECTOR_PAIRS if p[:2] != ("AU25", "AU26")
)


def realistic_noise_spec(
    n_frames: int = 30_000, n_videos: int = 800, seed: int = 0, au_noise_sd: float = 0.07, **overrides
) -> SynthSpec:
    """The issue-43 preset: co-activated AUs read by a noisy detector, like real py-feat tables.

    AUs co-activate through the shared expressions and, more tightly, in the :data:`COACTIVATED_AUS` pairs
    (``au_coactivation`` 1: AU09/AU10's within-video correlation ~0.9), with 0.7 of the generator's within-video
    activity (``au_activity``: the error's sd relative to the AUs' as in the issue's tables); the detector's error has
    sd ``au_noise_sd``, AR(1) 0.7 in time and correlation 0.5 within :data:`PRESET_NOISE_PAIRS`.
    ``au_noise_sd=0`` is its
    no-noise control: the same frames, meshes and true AUs. ``overrides``: any other :class:`SynthSpec` field
    (e.g. ``instrument_noise_sd=0.07``, ``layout="pyfeat"``).
    """
    fields = {
        "au_coactivation": 1.0,
        "au_activity": 0.7,
        "au_noise_ar": 0.7,
        "au_noise_correlation": PRESET_NOISE_PAIRS,
    }
    return SynthSpec(
        n_frames=n_frames, n_videos=n_videos, seed=seed, au_noise_sd=au_noise_sd, **{**fields, **overrides}
    )


def identity_resemblance(coef: np.ndarray, identity_basis: np.ndarray) -> np.ndarray:
    """Standardized resemblance of an identity shape to each AU field, as a map of the identity weights.

    With identity ``i = identity_basis.T @ c``, ``c ~ N(0, s^2 I)``, and AU field ``f_k`` (row k of ``coef``),
    the AU intensity that best explains ``i`` along ``f_k`` is ``r_k = f_k . i / |f_k|^2``;
    ``z = G @ (c / s)`` is ``r`` in units of its population standard deviation.

    Returns
    -------
    G : ndarray, shape (20, n_identity)
        Unit rows ``g_k / |g_k|``, ``g_k = identity_basis @ f_k``.
    """
    g = coef[: len(AU_COLUMNS)] @ identity_basis.T
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def generate_video(
    spec: SynthSpec,
    video: int,
    n_frames: int,
    coef: np.ndarray,
    intercept: np.ndarray,
    identity_basis: np.ndarray,
    latent_basis: np.ndarray,
    resemblance: np.ndarray | None = None,
    keep_canonical: bool = False,
    extra: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Frames of one video: AUs as recorded (``au``), the true AUs the mesh follows (``au_true``), pose (radians,
    model order), observed image-space meshes (n, 478, 3) and the video's AU baseline (zeros without coupling;
    ``resemblance`` from :func:`identity_resemblance`).

    With detector noise (``spec.au_noise_sd``) also ``au_error`` (n, 20): the error added to the recorded AUs before
    they are clipped to [0, 1]; with ``spec.instrument_noise_sd`` the second detector's AUs ``au2`` (n, 20). With
    ``keep_canonical`` the meshes before rotation, scale, shift and landmark noise, ``canonical`` (n, 478, 3) px:
    ``x @ coef + intercept + identity + latent`` (``+ extra``: (n, 1434) axis-major pixels more, e.g. the family
    truth's displacements, :mod:`aumesh.synthetic.family_truth`; None adds nothing and draws nothing).
    """
    rng = np.random.default_rng([spec.seed, video])
    propensity = rng.uniform(0.3, 1.6, size=5 + len(AU_COLUMNS))
    au = _au_intensities(rng, n_frames, propensity)
    if spec.au_coactivation:  # no random draw: every table without it stays bit-identical
        au = coactivate(au, spec.coactivated_aus, spec.au_coactivation)
    if spec.au_activity != 1.0:  # less (or more) expression within each video, its mean level kept
        au = np.clip(au.mean(axis=0) + spec.au_activity * (au - au.mean(axis=0)), 0.0, 1.0)
    true_au = au
    mean_pose = np.deg2rad(
        [rng.normal(0, spec.pitch_sd_deg), rng.normal(0, spec.yaw_sd_deg), rng.normal(0, spec.roll_sd_deg)]
    )
    walk = np.cumsum(rng.normal(0, np.deg2rad(1.5), size=(n_frames, 3)), axis=0)
    pose = mean_pose + walk - walk.mean(0)  # (n, 3) Pitch, Yaw, Roll
    if spec.profile_rate > 0:  # off: not a single draw more (every existing table stays bit-identical)
        pose[:, 1] = profile_yaw(spec, video, pose[:, 1])
    x = np.column_stack([au, pose, (pose[:, :, None] * au[:, None, :]).reshape(n_frames, -1)])
    identity_sd = spec.identity_scale * spec.px_per_iod
    weights = rng.normal(0, identity_sd, size=identity_basis.shape[0])
    identity = identity_basis.T @ weights
    latent = (
        rng.normal(0, spec.unexplained_scale * spec.px_per_iod, size=(n_frames, latent_basis.shape[0])) @ latent_basis
    )
    canonical = x @ coef + intercept + identity + latent  # (n, 1434) axis-major, pixels
    if extra is not None:
        canonical = canonical + extra
    canonical = canonical.reshape(n_frames, 3, N_VERTICES).transpose(0, 2, 1)
    centre = canonical.mean(axis=1, keepdims=True)
    rot = Rotation.from_euler("xyz", pose).as_matrix()  # the card's convention for the recorded pose
    scale = rng.uniform(0.7, 1.5) * np.exp(rng.normal(0, 0.02, size=n_frames))
    shift = np.array([320.0, 240.0, 0.0]) + rng.normal(0, [60, 40, 5]) + np.cumsum(rng.normal(0, 0.5, (n_frames, 3)), 0)
    observed = scale[:, None, None] * np.einsum("fvj,fij->fvi", canonical - centre, rot) + shift[:, None, :]
    observed += rng.normal(0, spec.noise_px, size=observed.shape)
    failed = rng.random(n_frames) < spec.landmark_failure_rate
    if failed.any():  # a tracking failure drags part of the face away
        k = int(failed.sum())
        observed[failed] += rng.normal(0, 0.25 * spec.px_per_iod, size=(k, 1, 3)) * (
            rng.random((k, N_VERTICES, 1)) < 0.4
        )
    baseline = np.zeros(len(AU_COLUMNS))
    if spec.identity_au_coupling:  # the detector reads the resting face as expression; the mesh follows the true AUs
        if resemblance is None:
            raise ValueError("identity_au_coupling needs resemblance (identity_resemblance(coef, identity_basis))")
        baseline = spec.identity_au_coupling * np.logaddexp(0.0, resemblance @ weights / identity_sd)
        baseline = np.minimum(baseline, 0.9)
        au = baseline + (1.0 - baseline) * au
    out = {"au": au, "au_true": true_au, "pose": pose, "mesh": observed, "landmark_failure": failed}
    out["au_baseline"] = baseline
    if spec.au_noise_sd > 0 or spec.instrument_noise_sd > 0:  # off: not a single draw more
        out.update(detector_readings(spec, video, au))
    if keep_canonical:
        out["canonical"] = canonical
    return out


def coactivate(au: np.ndarray, pairs: tuple[tuple[str, str, float], ...], strength: float) -> np.ndarray:
    """AUs (n, 20) with the follower of each ``(leader, follower, weight)`` pair following the leader, in order:
    ``b <- (1 - c) b + c a``, ``c = strength * weight`` in [0, 1] (so the AUs stay in [0, 1])."""
    out = au.copy()
    for a, b, weight in pairs:
        if a not in AU_COLUMNS or b not in AU_COLUMNS or a == b:
            raise ValueError(f"coactivated_aus: ({a!r}, {b!r}) need two different AU columns ({', '.join(AU_COLUMNS)})")
        c = strength * weight
        if not 0.0 <= c <= 1.0:
            raise ValueError(f"coactivated_aus: ({a}, {b}) strength au_coactivation x weight = {c:g}, need 0-1")
        i, j = AU_COLUMNS.index(a), AU_COLUMNS.index(b)
        out[:, j] = (1.0 - c) * out[:, j] + c * out[:, i]
    return out


def detector_readings(spec: SynthSpec, video: int, read: np.ndarray) -> dict[str, np.ndarray]:
    """What noisy detectors record of the AUs ``read`` (n, 20) a noise-free one would: ``au`` = ``read`` + the
    error ``au_error`` (:func:`au_noise.ar1_noise`, stream ``[seed, video, 11]``), and ``au2`` = ``read`` + a second
    detector's independent error (stream ``[seed, video, 12]``; same AR(1) and cross-AU correlation), when their sds
    are positive.

    Both are clipped to [0, 1]: the data contract refuses AUs outside py-feat's 0-1 range
    (``aumesh.data.contract.AU_RANGE``), as real detectors' probabilities never leave it, so unclipped tables would
    not ingest. Clipping makes the error non-classical near 0, where most AUs sit (it cuts the negative errors there),
    so the recorded error's within-video covariance is a little smaller than :func:`au_noise.au_error_covariance`
    (``au_sigma_u_within``, the error before clipping); the truth file holds both (``au_sigma_u_within_recorded``:
    measured from the recorded AUs). Measured on :func:`realistic_noise_spec` (benchmarks/au_noise_tables.py): 2.2 %
    of the values clipped, the recorded error's sd 0.064 against 0.065, and every AU field's cosine to the truth the
    same with and without clipping within 0.002.
    """
    n = len(read)
    chol = np.linalg.cholesky(au_noise.correlation_matrix(spec.au_noise_correlation))
    out: dict[str, np.ndarray] = {}
    if spec.au_noise_sd > 0:
        e = au_noise.ar1_noise(
            np.random.default_rng([spec.seed, video, 11]), n, spec.au_noise_sd, spec.au_noise_ar, chol
        )
        out["au"], out["au_error"] = np.clip(read + e, 0.0, 1.0), e
    if spec.instrument_noise_sd > 0:
        e2 = au_noise.ar1_noise(
            np.random.default_rng([spec.seed, video, 12]), n, spec.instrument_noise_sd, spec.au_noise_ar, chol
        )
        out["au2"] = np.clip(read + e2, 0.0, 1.0)
    return out


@dataclass(frozen=True)
class FamilySource:
    """What :func:`write_tables` needs to write the blendshape and emotion families (issue 46): built by
    :func:`aumesh.synthetic.family_truth.family_source` (which depends on this module, not the other way round).

    ``fields``: ``"blendshapes"`` (52, 1434) and ``"emotions"`` (7, 1434), axis-major pixels of the canonical frame;
    ``draw(rng, n)``: ``n`` frames' blendshapes (n, 52) and emotions (n, 7); ``truth``: arrays the truth NPZ adds."""

    fields: dict[str, np.ndarray]
    draw: Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]
    truth: dict[str, np.ndarray]


def write_tables(
    out_dir: str | Path, spec: SynthSpec, truth_path: str | Path | None = None, families: FamilySource | None = None
) -> dict:
    """Write synthetic frame tables under ``out_dir``; optionally save the ground truth as an NPZ.

    With ``families`` (``aumesh synth --families``, issue 46: :func:`aumesh.synthetic.family_truth.family_source`)
    each table also holds the 52 blendshapes and 7 emotions (``core.families.BLENDSHAPE_COLUMNS``,
    ``EMOTION_COLUMNS``: MPDetector's names) after the pose, drawn per video from their own random stream
    (``[seed, video, 6]``: blendshapes in [0, 1], emotions a softmax), independent of the AUs, and each canonical mesh
    moves by their known fields (:func:`family_displacement`); the truth NPZ then also holds ``families.truth``
    (``blendshape_fields`` (52, 1434), ``emotion_fields`` (7, 1434), ``blendshape_columns``, ``emotion_columns``).
    Without it nothing more is drawn: the tables and truth are byte-identical to the generator before it.

    The truth NPZ holds ``coef`` (83, 1434) and ``intercept`` of the true map in the canonical template
    frame (px), ``au_fields`` (20, 1434) = its AU rows (the true AU displacement fields), ``au_columns``,
    ``au_baseline`` (n_videos, 20) (each video's AU baseline; zeros without ``identity_au_coupling``),
    ``template_px``, ``anchor_indices`` and ``spec``. With detector noise (``spec.au_noise_sd > 0``; only then, so a
    noise-free truth file is byte-identical to before) also ``au_sigma_u_within`` (20, 20): the generator's own
    within-video error covariance (:func:`au_noise.au_error_covariance`; save it for ``model.eiv.sigma_u`` with
    :func:`au_noise.save_sigma_u`), ``au_sigma_u_within_recorded`` (20, 20): the same measured from the recorded AUs
    (after clipping to [0, 1]) minus the true ones, and ``frames_per_video``; with ``instrument_noise_sd > 0``
    ``au2_sigma_u_within`` (the second detector's).

    Returns a summary (files, frames, videos, landmark failures).
    """
    from aumesh.geometry import face

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if spec.layout not in ("columns", "pyfeat"):
        raise ValueError(f"synth layout {spec.layout!r}: use 'columns' or 'pyfeat'")
    if spec.au_noise_sd < 0 or spec.instrument_noise_sd < 0:
        raise ValueError(
            f"synth au_noise_sd={spec.au_noise_sd}, instrument_noise_sd={spec.instrument_noise_sd}: need >= 0 (0 = off)"
        )
    rng = np.random.default_rng(spec.seed)
    counts = _frames_per_video(spec, rng)
    coef, intercept, columns = true_coefficients(spec)
    template = face.canonical_template()
    identity_basis = flatten_axis_major(_smooth_fields(template, 10, np.random.default_rng(20_000 + spec.seed)))
    latent_basis = flatten_axis_major(_smooth_fields(template, 6, np.random.default_rng(30_000 + spec.seed)))
    latent_basis[
        :, np.r_[ANCHOR_INDICES, np.add(ANCHOR_INDICES, N_VERTICES), np.add(ANCHOR_INDICES, 2 * N_VERTICES)]
    ] = 0.0
    resemblance = identity_resemblance(coef, identity_basis)

    files, failures, file_no, video, baselines = [], 0, 0, 0, []
    n_au = len(AU_COLUMNS)
    recorded_error = np.zeros((n_au, n_au))  # within-video sum of squares of recorded - true AUs
    while video < spec.n_videos:
        parts, rows = [], 0
        while video < spec.n_videos and (rows == 0 or rows + counts[video] <= spec.frames_per_file):
            n = int(counts[video])
            family = None if families is None else families.draw(np.random.default_rng([spec.seed, video, 6]), n)
            moved = None if family is None or families is None else family_displacement(family, families.fields)
            g = generate_video(spec, video, n, coef, intercept, identity_basis, latent_basis, resemblance, extra=moved)
            if family is not None:
                g["blendshapes"], g["emotions"] = family
            parts.append((video, g))
            rows += int(counts[video])
            video += 1
        files.append(_write_file(out_dir / f"frames_{file_no:04d}.parquet", parts, spec.layout))
        failures += sum(int(p["landmark_failure"].sum()) for _, p in parts)
        baselines += [p["au_baseline"] for _, p in parts]
        if spec.au_noise_sd > 0:
            for _, p in parts:
                d = p["au"] - p["au_baseline"] - (1.0 - p["au_baseline"]) * p["au_true"]
                d -= d.mean(axis=0)
                recorded_error += d.T @ d
        file_no += 1
    if truth_path is not None:
        noise: dict[str, np.ndarray] = {}
        if spec.au_noise_sd > 0:
            noise["au_sigma_u_within"] = au_noise.au_error_covariance(spec, counts)
            noise["au_sigma_u_within_recorded"] = recorded_error / counts.sum()
            noise["frames_per_video"] = counts
        if spec.instrument_noise_sd > 0:
            noise["au2_sigma_u_within"] = au_noise.au_error_covariance(spec, counts, detector=2)
        atomic_savez(
            truth_path,
            coef=coef,
            intercept=intercept,
            feature_columns=np.array(columns),
            au_fields=coef[: len(AU_COLUMNS)],
            au_columns=np.array(AU_COLUMNS),
            au_baseline=np.array(baselines),
            template_px=template * spec.px_per_iod,
            anchor_indices=np.array(ANCHOR_INDICES, dtype=np.int32),
            spec=np.array(repr(_spec_record(spec))),
            **noise,
            **({} if families is None else families.truth),
        )
    return {
        "files": [str(f) for f in files],
        "n_frames": int(counts.sum()),
        "n_videos": spec.n_videos,
        "landmark_failures": failures,
    }


def family_displacement(family: tuple[np.ndarray, np.ndarray], fields: dict[str, np.ndarray]) -> np.ndarray:
    """(n, 1434) axis-major pixels the families move each canonical mesh by: ``blendshapes @ fields + emotions @
    fields`` (:func:`aumesh.synthetic.family_truth.family_truth_fields`)."""
    return family[0] @ fields["blendshapes"] + family[1] @ fields["emotions"]


def write_truth_sigma_u(truth_path: str | Path, name: str = "sigma_u.npy") -> Path:
    """Save the truth file's ``au_sigma_u_within`` as ``name`` beside it (the ``.npy`` ``model.eiv.sigma_u`` reads).

    Raises
    ------
    ValueError
        The truth file has no ``au_sigma_u_within`` (its tables were written without ``au_noise_sd``).
    """
    truth_path = Path(truth_path)
    with np.load(truth_path) as truth:
        if "au_sigma_u_within" not in truth.files:
            raise ValueError(
                f"{truth_path}: no au_sigma_u_within (tables written without detector noise). "
                f"Fix: write them with SynthSpec(au_noise_sd=...) (aumesh synth --au-noise-sd SD)"
            )
        sigma = truth["au_sigma_u_within"]
    return au_noise.save_sigma_u(truth_path.with_name(name), sigma)


def _write_file(path: Path, parts: list[tuple[int, dict]], layout: str) -> Path:
    meshes = np.concatenate([p["mesh"] for _, p in parts]).astype(np.float32)
    au = np.concatenate([p["au"] for _, p in parts])
    pose = np.concatenate([p["pose"] for _, p in parts])
    vids = np.concatenate([np.full(len(p["au"]), f"vid{v:06d}") for v, p in parts])
    frames = np.concatenate([np.arange(len(p["au"])) for _, p in parts])
    data: dict[str, np.ndarray] = {"input": np.char.add(np.char.add("videos/", vids), ".mp4"), "frame": frames}
    if layout == "columns":
        data["video_id"] = vids
    data["FaceScore"] = np.full(len(frames), 0.99)
    for j, name in enumerate(AU_COLUMNS):
        data[name] = au[:, j]
    if "au2" in parts[0][1]:  # the second detector's AUs (SynthSpec.instrument_noise_sd)
        au2 = np.concatenate([p["au2"] for _, p in parts])
        for j, name in enumerate(INSTRUMENT_COLUMNS):
            data[name] = au2[:, j]
    for name in ("Pitch", "Roll", "Yaw"):  # py-feat's Fex order; the model's is Pitch, Yaw, Roll
        data[name] = pose[:, POSE_COLUMNS.index(name)]
    if "blendshapes" in parts[0][1]:  # aumesh synth --families: the families under MPDetector's (the family's) names
        from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS

        for key, names in (("blendshapes", BLENDSHAPE_COLUMNS), ("emotions", EMOTION_COLUMNS)):
            values = np.concatenate([p[key] for _, p in parts])
            for j, name in enumerate(names):
                data[name] = values[:, j]
    if layout == "columns":
        flat = np.asfortranarray(meshes.reshape(len(meshes), -1))  # contiguous columns: Arrow copies none of them
        for i in range(N_VERTICES):  # interleaved, as py-feat stores them
            for a, axis in enumerate("xyz"):
                data[f"{axis}_{i}"] = flat[:, 3 * i + a]
    table = pa.table(data)
    with atomic_path(path, suffix=".parquet") as tmp:
        pq.write_table(table, tmp, row_group_size=8192, compression="zstd")
    if layout == "pyfeat":
        with atomic_path(path.with_suffix(".npy"), suffix=".npy") as tmp:
            np.save(tmp, meshes)
    return path
