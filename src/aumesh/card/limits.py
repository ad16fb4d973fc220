"""What a release's data can support: the card's machine-readable ``warnings`` and its "Limits of this release".

:func:`release_warnings` reads a ``model_card.json`` dict (and, when given, the FACS direction verdicts and the
size of each AU's field) and returns one ``{"code", "message", "do_not", ...details}`` per limit found;
:func:`limits_section` turns them into the card's Markdown section. Both are pure; the release stage
(:func:`aumesh.stages.release.main`) calls them after the direction report.

Fields written by other parts of the pipeline (``data.people``, ``data.unsupported_inputs``, ``data.input_ranges``,
``data.detector``) are read when present; a card without them simply gets no warning of that kind.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from aumesh.card.identification import identification_warning
from aumesh.card.markdown import md_text
from aumesh.data.face_track import AMBIGUOUS_AREA_RATIO

# ---------------------------------------------------------------------------------------------------- thresholds
#: Fewer training frames than this many per feature is "small data". The reference card fits 83 features on 344,418
#: frames (~4,150 per feature) and is stable across folds (R² 0.2443 ± 0.0034); issue 41's single-presenter set, 472
#: frames for 83 features (5.7 per feature), overfits (R² 0.37 ± 0.40, one fold -0.19). Frames of one video at 25-30
#: fps are near-duplicates, so a frame carries far less than one independent observation: 50 per feature is the
#: usual 10-20 observations per predictor of regression practice, times a few for that correlation.
MIN_FRAMES_PER_FEATURE = 50
#: Fewer videos than this is "few videos" (the reference has 9,978). CV holds out whole videos: below 50, a fold of a
#: 3-fold GroupKFold tests on at most 16 clips, and its R² and the field reliability speak for those clips.
MIN_VIDEOS = 50
#: Fewer distinct people than this (py-feat's ``Identity`` labels, ``data.people.identity_labels``) is "few people":
#: each AU field then mixes what the AU does with how these few faces are built and move; 10 is the smallest set
#: that spans some variety of face shape, far below the reference's thousands of celebrities.
MIN_PEOPLE = 10
#: An AU field whose cosine across disjoint video subsets (``cv.au_reliability``) is below 0.5 (fields more than
#: 60 degrees apart) is mostly noise of the subset it was fitted on.
MIN_RELIABILITY = 0.5
#: The fold R² spread is "large" when a fold's R² is negative or the std exceeds this fraction of the mean: the
#: reference's std is 1.4 % of its mean; 25 % means a new set of videos may see a very different accuracy.
MAX_RELATIVE_FOLD_STD = 0.25
#: More than this fraction of the frames dropped by the pose filter: the data is mostly about poses the release
#: does not model, and what is left may be a biased (frontal-only) part of each video.
MAX_POSE_DROPPED = 0.25
#: An AU whose field (largest vertex displacement at intensity 1) is more than this many times the median over the
#: AUs with a field is "implausible": on the synthetic and demo releases the largest AU (AU26, jaw drop) is 2.5x the
#: median; issue 41's AU09, never above 0.035 in its training data, moved vertices by 1.3 inter-ocular distances,
#: ~25x. Shared with the figures (:mod:`aumesh.card.render`).
IMPLAUSIBLE_FIELD_FACTOR = 5.0


#: How the warnings name an input family's inputs (issue 46: the family releases' cards reuse these checks):
#: family -> (one input, the inputs, the smaller designs to suggest, what the inputs stand for).
INPUT_WORDS: dict[str, tuple[str, str, str, str]] = {
    "au": ("AU", "AUs", "features=au or au_pose", "how AUs move a face"),
    "blendshapes": (
        "blendshape",
        "blendshapes",
        "families.blendshapes.features=blendshapes or blendshapes_pose",
        "how MediaPipe's blendshapes move a face",
    ),
    "emotions": (
        "emotion",
        "emotions",
        "families.emotions.features=emotions or emotions_pose",
        "how emotions move a face",
    ),
}


# ---------------------------------------------------------------------------------------------------- field sizes
def au_field_sizes(disp: np.ndarray) -> np.ndarray:
    """Largest vertex displacement of each AU's field.

    Parameters
    ----------
    disp : ndarray, shape (n_aus, 478, 3)
        Displacement of each AU at intensity 1 (any units; the card's figures use inter-ocular distances).

    Returns
    -------
    ndarray, shape (n_aus,)
    """
    d = np.asarray(disp, dtype=np.float64)
    return np.linalg.norm(d, axis=-1).max(axis=-1) if d.size else np.zeros(len(d))


def implausible_fields(sizes: np.ndarray, factor: float = IMPLAUSIBLE_FIELD_FACTOR) -> np.ndarray:
    """Which fields are more than ``factor`` x the median size of the AUs that move at all.

    Parameters
    ----------
    sizes : ndarray, shape (n_aus,)
        :func:`au_field_sizes`.

    Returns
    -------
    ndarray of bool, shape (n_aus,)
        False everywhere when fewer than 3 AUs move (no median to compare with).
    """
    s = np.asarray(sizes, dtype=np.float64)
    if np.count_nonzero(s > 0) < 3:
        return np.zeros(s.shape, dtype=bool)
    return s > factor * moving_median(s)


def moving_median(sizes: np.ndarray) -> float:
    """The median size of the fields that move at all (``sizes`` > 0; 0.0 when none does): what
    :func:`implausible_fields` compares each field with, and what the card and figures quote."""
    s = np.asarray(sizes, dtype=np.float64)
    moving = s[s > 0]
    return float(np.median(moving)) if moving.size else 0.0


def au_field_iod(arrays: Mapping[str, Any]) -> dict[str, float]:
    """Each AU's largest vertex displacement at intensity 1 (:func:`au_field_sizes`), in inter-ocular distances of the
    release's ``mean_aligned_mesh`` (:func:`aumesh.card.directions.au_displacements`): the sizes
    :func:`release_warnings` judges."""
    from aumesh.card.directions import au_displacements

    disp, _, columns = au_displacements(arrays)
    return {au: round(float(size), 6) for au, size in zip(columns, au_field_sizes(disp), strict=True)}


# ---------------------------------------------------------------------------------------------------- warnings
def _warning(code: str, message: str, do_not: str, **details: Any) -> dict[str, Any]:
    return {"code": code, "message": message, "do_not": do_not, **details}


def _fmt_list(names: Sequence[str]) -> str:
    return ", ".join(names)


def _verb(names: Sequence[str], one: str, many: str) -> str:
    """``one`` for a single name, ``many`` for several ("AU09 moves", "AU09, AU43 move")."""
    return one if len(names) == 1 else many


def _data_warnings(data: Mapping[str, Any], n_features: int | None, family: str = "au") -> list[dict[str, Any]]:
    _, _, smaller, meaning = INPUT_WORDS[family]
    out = []
    n_frames, n_videos = data.get("n_frames"), data.get("n_videos")
    if n_frames is not None and n_features:
        per = n_frames / n_features
        if per < MIN_FRAMES_PER_FEATURE:
            out.append(
                _warning(
                    "small_data_frames",
                    f"{n_frames:,} training frames for {n_features} features ({per:.1f} per feature; at least "
                    f"{MIN_FRAMES_PER_FEATURE} wanted, the reference card has ~4,150): the fit can overfit, and "
                    f"consecutive frames of a video add little information; more data, or fewer features "
                    f"({smaller}), would help",
                    f"as a general model of {meaning}",
                    n_frames=n_frames,
                    n_features=n_features,
                    frames_per_feature=round(per, 2),
                    threshold=MIN_FRAMES_PER_FEATURE,
                )
            )
    if n_videos is not None and n_videos < MIN_VIDEOS:
        out.append(
            _warning(
                "few_videos",
                f"{n_videos:,} training videos (at least {MIN_VIDEOS} wanted, the reference card has 9,978): "
                "cross-validation holds out whole videos, so each fold's R² rests on a handful of clips",
                "to claim accuracy on new videos from the CV numbers",
                n_videos=n_videos,
                threshold=MIN_VIDEOS,
            )
        )
    people = (data.get("people") or {}).get("identity_labels")
    if people is not None and people < MIN_PEOPLE:
        who = "one person" if people == 1 else f"{people} people"
        out.append(
            _warning(
                "few_people",
                f"{who} in the training data (py-feat's Identity labels): every {INPUT_WORDS[family][0]} field mixes "
                f"what the {INPUT_WORDS[family][0]} does with "
                + ("how this face is built and moves" if people == 1 else "how these faces are built and move"),
                "as a model of other people's faces, or of a population",
                identity_labels=people,
                threshold=MIN_PEOPLE,
            )
        )
    return out


def _unsupported_warning(data: Mapping[str, Any]) -> list[dict[str, Any]]:
    unsupported = list(data.get("unsupported_inputs") or [])
    if not unsupported:
        return []
    ranges = data.get("input_ranges") or {}
    p99 = {au: ranges[au]["p99"] for au in unsupported if au in ranges and ranges[au].get("p99") is not None}
    seen = "; ".join(f"{au} p99 {v:.3g}" for au, v in p99.items())
    return [
        _warning(
            "unsupported_inputs",
            f"{_fmt_list(unsupported)} {_verb(unsupported, 'barely occurs', 'barely occur')} in the training data "
            "(99th percentile below 0.05"
            + (f": {seen}" if seen else "")
            + f"): {_verb(unsupported, 'its field is', 'their fields are')} extrapolation, unconstrained by the data",
            f"to drive or interpret {_fmt_list(unsupported)}",
            aus=unsupported,
            p99=p99,
        )
    ]


#: Spread of the per-frame input sum (max - min) under which a family's inputs count as summing to a constant
CONSTANT_SUM_SPREAD = 1e-3


def _sum_warning(data: Mapping[str, Any], family: str) -> list[dict[str, Any]]:
    """A family whose inputs sum to one value in every training frame (``data.input_sum``: py-feat's emotions are a
    softmax): its design is rank-deficient, so only differences between the inputs' fields are identified."""
    span = data.get("input_sum") or {}
    if not span or span["max"] - span["min"] > CONSTANT_SUM_SPREAD * max(1.0, abs(span["max"])):
        return []
    one, many, _, _ = INPUT_WORDS[family]
    total = 0.5 * (span["min"] + span["max"])
    return [
        _warning(
            "inputs_sum_constant",
            f"the {many} sum to {total:.3g} in every training frame (min {span['min']:.6g}, max {span['max']:.6g}): "
            f"the intercept is their sum, so only differences between {many}' fields are identified; the mesh of "
            f"one {one} with the others 0 (plot_face_mesh({family[:-1]}={{name: 0.8}})) holds a share of the fit's "
            f"arbitrary choice",
            f"to read one {one}'s field alone: give {many} that sum to {total:.3g} (e.g. the rest on neutral), "
            "or compare two of them",
            sum_min=span["min"],
            sum_max=span["max"],
        )
    ]


def _field_warnings(
    cv: Mapping[str, Any],
    au_directions: Mapping[str, str] | None,
    au_field_iod: Mapping[str, float] | None,
    constant: Sequence[str] = (),
    family: str = "au",
) -> list[dict[str, Any]]:
    """Reliability, FACS direction and field size; ``constant`` inputs (no field at all, their own warning) are not
    judged here: their zero field has cosine 0 and no direction, which says nothing about the data's noise."""
    out = []
    reliability = cv.get("au_reliability") or {}
    low = {au: round(float(v), 3) for au, v in reliability.items() if v < MIN_RELIABILITY and au not in constant}
    if low:
        out.append(
            _warning(
                "low_au_reliability",
                f"{_fmt_list(list(low))}: fields fitted on disjoint subsets of videos disagree (cosine "
                + ", ".join(f"{v:.2f}" for v in low.values())
                + f" < {MIN_RELIABILITY})",
                f"to interpret what {_fmt_list(list(low))} do{'es' if len(low) == 1 else ''} to a face",
                aus=list(low),
                reliability=low,
                threshold=MIN_RELIABILITY,
            )
        )
    directions = au_directions or {}
    for verdict, code, words in (
        (
            "fail",
            "au_direction_fail",
            ("moves against, or away from, what FACS describes", "move against, or away from, what FACS describes"),
        ),
        ("doubtful", "au_direction_doubtful", ("matches FACS only loosely", "match FACS only loosely")),
    ):
        aus = [au for au, v in directions.items() if v == verdict and au not in constant]
        if aus:
            out.append(
                _warning(
                    code,
                    f"{_fmt_list(aus)} {_verb(aus, *words)} (FACS direction check, section 'AU directions')",
                    f"as FACS-faithful animation or illustration of {_fmt_list(aus)}",
                    aus=aus,
                )
            )
    if au_field_iod:
        names = list(au_field_iod)
        sizes = np.array([au_field_iod[n] for n in names], dtype=np.float64)
        flagged = implausible_fields(sizes)
        if flagged.any():
            median = moving_median(sizes)
            big = {n: round(float(s), 3) for n, s, f in zip(names, sizes, flagged, strict=True) if f}
            out.append(
                _warning(
                    "implausible_fields",
                    f"{_fmt_list(list(big))} {_verb(list(big), 'moves', 'move')} vertices by "
                    + ", ".join(f"{v:.2f}" for v in big.values())
                    + f" inter-ocular distances at intensity 1, more than {IMPLAUSIBLE_FIELD_FACTOR:g}x the median "
                    f"{INPUT_WORDS[family][0]} ({median:.3f}): likely an {INPUT_WORDS[family][0]} the data barely "
                    "varied, given a huge and meaningless field",
                    f"to drive {_fmt_list(list(big))} (the figures show {_verb(list(big), 'it', 'them')} greyed out)",
                    aus=list(big),
                    field_iod=big,
                    median_field_iod=round(median, 4),
                    factor=IMPLAUSIBLE_FIELD_FACTOR,
                )
            )
    return out


def _cv_warning(cv: Mapping[str, Any]) -> list[dict[str, Any]]:
    folds = [float(v) for v in cv.get("r2_folds") or []]
    if not folds:
        return []
    mean = float(cv.get("r2_mean", np.mean(folds)))
    std = float(cv.get("r2_std", np.std(folds)))
    negative = [round(v, 4) for v in folds if v < 0]
    relative = std / abs(mean) if mean != 0 else float("inf")
    if not negative and mean > 0 and relative <= MAX_RELATIVE_FOLD_STD:
        return []
    why = f"one or more folds below 0 ({', '.join(f'{v:.3f}' for v in negative)})" if negative else ""
    if mean <= 0 or relative > MAX_RELATIVE_FOLD_STD:
        why += ("; " if why else "") + f"std {std:.3f} is {relative:.0%} of the mean {mean:.3f}"
    return [
        _warning(
            "fold_spread",
            f"cross-validated R² varies widely between folds: {why}; folds " + ", ".join(f"{v:.3f}" for v in folds),
            "to quote the mean CV R² as this model's accuracy on new videos without its spread",
            r2_folds=folds,
            r2_mean=mean,
            r2_std=std,
            max_relative_std=MAX_RELATIVE_FOLD_STD,
        )
    ]


def _pose_warning(counts: Mapping[str, Any]) -> list[dict[str, Any]]:
    dropped, frames_in = counts.get("dropped_pose"), counts.get("frames_in")
    if dropped is None:
        return []
    fraction = counts.get("dropped_pose_fraction")
    if fraction is None:
        fraction = dropped / frames_in if frames_in else 0.0
    if fraction <= MAX_POSE_DROPPED:
        return []
    return [
        _warning(
            "pose_filter_dropped",
            f"the pose filter dropped {dropped:,} frames ({fraction:.0%}): most of the data shows poses this "
            "release does not model, and the frames kept may be an unrepresentative part of each video",
            "for heads turned beyond the pose filter's limits",
            dropped_pose=dropped,
            fraction=round(float(fraction), 4),
            threshold=MAX_POSE_DROPPED,
        )
    ]


def _faces_warning(counts: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Frames where two faces were about the same size (the ingest's ``frames_ambiguous_faces``,
    :mod:`aumesh.data.face_track`): the face kept there is the one continuing the video's track, a rule that can
    follow the wrong person (crossing faces, a person leaving) where py-feat's Identity does not tell them apart."""
    n = int(counts.get("frames_ambiguous_faces") or 0)
    if not n:
        return []
    frames = counts.get("frames_out") or counts.get("frames_in")
    share = f" ({n / frames:.1%} of the frames)" if frames else ""
    return [
        _warning(
            "ambiguous_faces",
            f"{n:,} frames{share} showed two or more faces of about the same size (the second box at least "
            f"{AMBIGUOUS_AREA_RATIO:g} of the largest's area), so the largest face could not tell the video's person; "
            "the face continuing the video's track was kept (py-feat's Identity, else the nearest box), which can "
            "follow the wrong person where faces cross or one leaves",
            "as if every video's frames were one person's without checking those videos",
            frames_ambiguous_faces=n,
            ratio=AMBIGUOUS_AREA_RATIO,
        )
    ]


def _degenerate_warnings(data: Mapping[str, Any]) -> list[dict[str, Any]]:
    degenerate = data.get("degenerate") or {}
    constant = dict(degenerate.get("constant_inputs") or {})
    if not constant:
        return []
    names = list(constant)
    return [
        _warning(
            "constant_inputs",
            f"{_fmt_list(names)} never varied in the training data: their coefficients are 0",
            f"to show what {_fmt_list(names)} do (the release moves nothing for them)",
            inputs=names,
        )
    ]


def _detector_warning(data: Mapping[str, Any], family: str = "au") -> list[dict[str, Any]]:
    detector = data.get("detector") or {}
    name = detector.get("name")
    if name not in ("mixed", "unknown"):
        return []
    one, many = INPUT_WORDS[family][:2]
    if family == "au":
        mixed = (
            "tables from several py-feat detectors: their AUs mean different things (Detectorv2: presence "
            "probabilities; MPDetector: a linear map of MediaPipe's blendshapes)"
        )
    else:  # Detectorv2's own network writes both families; MPDetector takes them from MediaPipe's models
        mixed = (
            f"tables from several py-feat detectors: their {many} come from different networks (Detectorv2's "
            f"multitask network; MPDetector's MediaPipe models), so one value is not one expression across the data"
        )
    what = (
        mixed
        if name == "mixed"
        else f"tables of unknown origin (not a py-feat detector export): the {many}' scale and meaning are unknown"
    )
    return [
        _warning(
            f"detector_{name}",
            what,
            f"with {one} values from a detector other than the training data's, as if they were the same scale",
            detector=name,
        )
    ]


def release_warnings(
    card: Mapping[str, Any],
    au_directions: Mapping[str, str] | None = None,
    au_field_iod: Mapping[str, float] | None = None,
    family: str = "au",
) -> list[dict[str, Any]]:
    """The limits of a release, machine-readable: ``model_card.json``'s ``warnings``.

    Parameters
    ----------
    card : mapping
        ``model_card.json`` (:func:`aumesh.pipeline.release.build_card`): ``data`` (``n_frames``, ``n_videos``,
        ``counts``, ``degenerate``, and when present ``people``, ``unsupported_inputs``, ``input_ranges``,
        ``detector``), ``cv`` (``r2_folds``, ``r2_mean``, ``r2_std``, ``au_reliability``), ``model.n_features``.
    au_directions : mapping, optional
        AU -> "pass" | "doubtful" | "fail" (the card's ``au_directions``; read from ``card`` when not given).
    au_field_iod : mapping, optional
        AU -> largest vertex displacement at intensity 1, inter-ocular distances (:func:`au_field_sizes`); for a
        family release, each of its inputs'.
    family : str
        The input family the release maps (:data:`INPUT_WORDS`): the words of the messages; the checks are the same.

    Returns
    -------
    list of dict
        Each ``{"code", "message", "do_not", ...details}``; ``message`` says what was found, ``do_not`` what the
        release should not be used for. Empty when no limit was found.
    """
    data = card.get("data") or {}
    cv = card.get("cv") or {}
    n_features = (card.get("model") or {}).get("n_features")
    directions = au_directions if au_directions is not None else card.get("au_directions")
    return [
        *_data_warnings(data, n_features, family),
        *_unsupported_warning(data),
        *_sum_warning(data, family),
        *_field_warnings(
            cv, directions, au_field_iod, list((data.get("degenerate") or {}).get("constant_inputs") or {}), family
        ),
        *_cv_warning(cv),
        *_pose_warning(data.get("counts") or {}),
        *_faces_warning(data.get("counts") or {}),
        *_degenerate_warnings(data),
        *_detector_warning(data, family),
        *identification_warning(card),
    ]


CHECKED = (
    "data size (frames, videos, people), AUs the data barely exercised, field size and reliability, FACS directions, "
    "fold spread, pose filter, constant inputs, detector, AU identification under detector noise"
)


#: What a family release's checks look at (:func:`release_warnings` with ``family``; no FACS or identification check)
CHECKED_FAMILY = (
    "data size (frames, videos, people), inputs the data barely exercised, field size, fold spread, pose filter, "
    "constant inputs, detector"
)


def limits_section(warnings: Sequence[Mapping[str, Any]], checked: str = CHECKED) -> list[str]:
    """The card's "## Limits of this release": one bullet per warning (what was found, what not to use it for), or
    one line saying that no limit was found; ``checked`` says what the checks looked at (:data:`CHECKED`,
    :data:`CHECKED_FAMILY`)."""
    lines = ["## Limits of this release", ""]
    if not warnings:
        return lines + [f"No limit found by the release's checks ({checked}).", ""]
    lines += [
        f"{len(warnings)} limit{'s' if len(warnings) != 1 else ''} found ({checked} checked); machine-readable in "
        "`model_card.json`'s `warnings`.",
        "",
    ]
    lines += [
        f"- **{md_text(w['code'])}**: {md_text(w['message'])}. Do not use this release {md_text(w['do_not'])}."
        for w in warnings
    ]
    return lines + [""]
