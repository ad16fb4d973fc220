"""What the card says about detector noise: the AU identification screen's section and warning, and the correction a
run applied (``model/eiv``). Pure functions of ``model_card.json``'s fields; docs/method.md has the equations."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from aumesh.card.markdown import md_code, md_text

SCREEN_TEXT = (
    "Detector noise in the AU intensities (errors correlated across AUs and lasting several frames) biases every "
    "least-squares field, and where two AUs co-activate it can turn the smaller field against the truth. The screen "
    "asks, for each AU, how large an isotropic detector noise (sd sigma, in intensity units) would have to be for the "
    "floored corrected fit to turn its field by more than 60 degrees (cosine below {turn:g} to the fitted field): "
    "sigma* (docs/method.md, eq. 6). An AU with sigma* < {flag:g} is flagged: detectors of today's accuracy could have "
    "reversed it, and nothing in these data separates it from its dominant partner (the AU whose field leaks into it "
    "most: correlation x relative field size). The partner group's field (both AUs moved together) is identified when "
    "its members are not. This is a screen, not a proof: it uses the data's own geometry, not the detector's real "
    "error; a flagged field may be right and an unflagged one wrong under a noise that is not isotropic. It is free "
    "(the within-video AU moments the fit already has) and on in every run."
)


def _sigma(value: float | None, grid_max: float | None) -> str:
    if value is None:
        return f"> {grid_max:g}" if grid_max is not None else "none"
    return f"{value:.3f}"


def identification_section(card: Mapping[str, Any]) -> list[str]:
    """``## AU identification under detector noise``: the screen's table (empty when the card has no screen)."""
    ident = card.get("au_identification") or {}
    if not ident:
        return []
    screen_cfg = ((card.get("config") or {}).get("model") or {}).get("identification") or {}
    flag, turn, grid_max = (
        screen_cfg.get("flag_below", 0.10),
        screen_cfg.get("turn_cosine", 0.5),
        screen_cfg.get("sigma_max"),
    )
    flagged = [au for au, v in ident.items() if v.get("flagged")]
    lines = [
        "## AU identification under detector noise",
        "",
        SCREEN_TEXT.format(turn=turn, flag=flag),
        "",
        (
            f"**{len(flagged)} of {len(ident)} AU fields flagged**: "
            + ", ".join(f"{au} (partner {ident[au]['partner']}, use {ident[au]['group']})" for au in flagged)
            if flagged
            else f"No AU field flagged (every sigma* >= {flag:g})."
        ),
        "",
        "| AU | sigma* | flagged | dominant partner | partner group | group sigma* |",
        "|---|---:|---|---|---|---:|",
    ]
    lines += [
        f"| {au} | {_sigma(v.get('sigma_star'), grid_max)} | {'**yes**' if v.get('flagged') else 'no'} | "
        f"{v.get('partner')} | {v.get('group')} | {_sigma(v.get('group_sigma_star'), grid_max)} |"
        for au, v in ident.items()
    ]
    return lines + [""]


def identification_warning(card: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The ``unidentified_au_fields`` warning: the AUs the screen flags, their partners and groups."""
    ident = card.get("au_identification") or {}
    flagged = {au: v for au, v in ident.items() if v.get("flagged")}
    if not flagged:
        return []
    screen_cfg = ((card.get("config") or {}).get("model") or {}).get("identification") or {}
    flag = screen_cfg.get("flag_below", 0.10)
    method = (((card.get("config") or {}).get("model") or {}).get("eiv") or {}).get("method", "none")
    names = list(flagged)
    groups = sorted({v["group"] for v in flagged.values()})
    remedy = (
        "; a correction is applied (model/eiv=" + method + "), so the fields are corrected with what the user brought"
        if method != "none"
        else "; the fields can be corrected with the detector's error covariance from a validation study "
        "(model/eiv=corrected) or a second detector's AUs on the same frames (model/eiv=instruments)"
    )
    return [
        {
            "code": "unidentified_au_fields",
            "message": (
                ", ".join(f"{au} (sigma* {v['sigma_star']:.3f}, partner {v['partner']})" for au, v in flagged.items())
                + f": a detector noise of sd below {flag:g} could turn these fields by more than 60 degrees, and the "
                "data cannot separate them from their partners; their partner groups "
                + ", ".join(groups)
                + " are identified (identification screen, a screen and not a proof)"
                + remedy
            ),
            "do_not": f"to interpret or drive {', '.join(names)} alone; drive the partner group instead",
            "aus": names,
            "partners": {au: v["partner"] for au, v in flagged.items()},
            "groups": groups,
            "sigma_star": {au: v["sigma_star"] for au, v in flagged.items()},
            "threshold": flag,
        }
    ]


def correction_lines(card: Mapping[str, Any]) -> list[str]:
    """Method bullets for a run corrected for detector noise (none for ``model/eiv=none``)."""
    eiv = (card.get("cv") or {}).get("eiv") or {}
    method = eiv.get("method", "none")
    if method == "none":
        return []
    if method == "corrected":
        head = (
            f"- **Corrected for detector noise**: floored corrected least squares on the within-video design "
            f"(X'X - n Sigma_u, each direction's reliability floored at {eiv.get('floor')}; docs/method.md eqs. 4-5) "
            f"with the AU detector's within-video error covariance {md_code(eiv.get('sigma_u'))} "
            f"(sha256 {md_code(str(eiv.get('sigma_u_sha256', ''))[:16])}), given from outside these tables"
        )
    else:
        head = (
            f"- **Corrected for detector noise**: within two-stage least squares with a second detector's AUs "
            f"{md_code(eiv.get('instrument_aus'))} as instruments (docs/method.md eq. 7)"
        )
    lines = [
        head,
        "- The corrected fit has a lower in-sample fit than least squares by design: its R² is not comparable with an "
        "uncorrected run's. The uncorrected fields of the same rows are released beside it (`coef_uncorrected`"
        + (", `coef_full_uncorrected`" if eiv.get("full") else "")
        + "); the R²-by-components curve is the uncorrected PLS's",
    ]
    strength = eiv.get("first_stage") or {}
    if strength:
        weak = [au for au, s in strength.items() if s.get("f", 0) < 10]
        lines.append(
            "- First-stage strength (within R² of each AU on the instruments): "
            + ", ".join(f"{md_text(au)} {s['r2']:.2f}" for au, s in strength.items())
            + (f"; **weak** (F < 10): {', '.join(weak)}" if weak else "; every F >= 10")
        )
    return lines
