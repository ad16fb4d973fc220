"""The user's tools on a release NPZ: ``render`` (the card's figures and AU-direction report), ``predict`` (meshes
from a table of AU rows), ``view`` (the offline viewer page), ``animate`` (a video's AUs as an animated glTF); and
the hidden ``dvc-plots-template`` (the offline page of ``dvc plots``, what ``make tools`` writes)."""

from __future__ import annotations

import sys
from pathlib import Path

from aumesh.cli.outputs import add_force, refuse_release_path


def _cmd_render(args) -> int:
    from aumesh.card.render import render_card
    from aumesh.core.errors import UserError

    refuse_release_path("--out", args.out, force=args.force)

    try:
        card = render_card(args.npz, args.out, args.cv)
    except UserError:
        raise
    except (FileNotFoundError, KeyError, ValueError) as err:  # any NPZ in the card's format: its faults are input
        raise UserError(str(err)) from err
    for path in card.paths:
        print(path)
    s = card.report["summary"]
    print(f"AU directions: {s['pass']} pass, {s['doubtful']} doubtful, {s['fail']} fail", file=sys.stderr)
    return 0


def _cmd_predict(args) -> int:
    from aumesh.pipeline.predict import predict_table

    refuse_release_path("--out", args.out, force=args.force)
    out, n = predict_table(args.release, args.table, args.out, args.ignore, strict=args.strict)
    print(f"wrote {n} mesh(es) to {out}")
    return 0


def _cmd_view(args) -> int:
    from aumesh.export import viewer
    from aumesh.model.family_inference import load_any_release

    refuse_release_path("--out", args.out, force=args.force)
    clips = viewer.table_clips(args.clip, args.video, args.fps, args.mesh_units) if args.clip else None
    out = viewer.write_viewer(load_any_release(args.npz), args.out, source=args.npz.name, clips=clips)
    played = f"; plays {len(clips)} video(s) of {args.clip.name}" if clips else ""
    print(f"wrote {out} (open it in a browser; works offline{played})")
    return 0


def _cmd_animate(args) -> int:
    from aumesh.export.gltf_clip import animate, default_release

    refuse_release_path("--out", args.out, force=args.force)
    summary = animate(
        args.table,
        args.release if args.release is not None else default_release(args.family),
        args.out,
        family=args.family,
        video=args.video,
        fps=args.fps,
        pose=args.pose,
        smooth_frames=args.smooth,
    )
    print(summary.line())
    return 0


def _cmd_dvc_plots_template(args) -> int:
    from aumesh.core.errors import UserError
    from aumesh.export import dvc_plots

    refuse_release_path("--out", args.out, force=args.force)
    try:
        out = dvc_plots.write_template(args.out)
    except FileNotFoundError as err:  # no vega in node_modules/: the message says `make tools`
        raise UserError(str(err)) from err
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB: vega, vega-lite, vega-embed inlined)")
    return 0


def add_parser(subparsers) -> None:
    """Add ``render``, ``predict``, ``view``, ``animate`` (and the unlisted ``dvc-plots-template``)."""
    p = subparsers.add_parser("render", help="render a release NPZ's figures and AU-direction report")
    p.add_argument("npz", type=Path, help="a release NPZ in the card's format (ours or another)")
    p.add_argument(
        "--out", type=Path, required=True, help="folder for the PNGs, au_directions.json and au_directions.md (created)"
    )
    p.add_argument(
        "--cv",
        type=Path,
        default=None,
        help="CV arrays NPZ with r2_per_vertex and vertex_error or the cumulative error curve, "
        "e.g. build/model/cv.npz "
        "(default: none, so no R² and error figures)",
    )
    add_force(p)
    p.set_defaults(func=_cmd_render)

    p = subparsers.add_parser(
        "predict",
        help="meshes from a CSV/parquet table of AU (+ pose) rows (py-feat's own output too), with a release NPZ",
    )
    p.add_argument(
        "table",
        type=Path,
        help="CSV or parquet, one row per mesh, columns by name: a whole py-feat table (MPDetector or "
        "Detectorv2; only AU01..AU43, Pitch, Yaw, Roll (radians) and FaceScore are read, all 20 AUs "
        "needed, AUs 0..1), or input columns only (missing AUs are 0; no Pitch, Yaw, Roll: pose 0). "
        "A row without a face (FaceScore 0, or every AU and pose value NaN) gets a NaN mesh and "
        "no_face=True; a row only partly NaN is an error. Pose beyond pi/2 is refused as degrees, "
        "Pitch/Yaw beyond the training range is a warning",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output file: .npz (meshes (N, 478, 3), no_face (N,)), or .obj / .ply for a one-row table",
    )
    p.add_argument(
        "--release",
        type=Path,
        default=Path("release/au_to_mesh_pls.npz"),
        help="release NPZ; a blendshape or emotion release (releases/<family>/*.npz) reads the table's 52 "
        "blendshape or 7 emotion columns by name instead of the AUs (default: %(default)s)",
    )
    p.add_argument(
        "--ignore",
        nargs="*",
        default=[],
        metavar="COLUMN",
        help="table columns to leave out, e.g. Pitch Yaw Roll for frontal meshes (default: none)",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="every column (after --ignore) must be an input column, AU01..AU43, Pitch, Yaw, Roll "
        "(default: other columns are ignored)",
    )
    add_force(p)
    p.set_defaults(func=_cmd_predict)

    p = subparsers.add_parser("view", help="write an offline interactive viewer (one HTML file) of a release NPZ")
    p.add_argument("npz", type=Path, help="release NPZ, e.g. release/au_to_mesh_pls.npz")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("viewer.html"),
        help="HTML file to write (default: %(default)s); needs three.js from `make tools`",
    )
    p.add_argument(
        "--clip",
        type=Path,
        metavar="TABLE",
        help="embed a py-feat table (CSV, .csv.gz or parquet) to play: the AUs over time beside the recorded mesh "
        "(default: none; the page can still open a CSV itself)",
    )
    p.add_argument("--video", help="with --clip: the one video to embed (default: every video of the table)")
    p.add_argument("--fps", type=float, help="with --clip: the video's frame rate (default: from approx_time, else 25)")
    p.add_argument(
        "--mesh-units",
        choices=("detector", "pixels"),
        default="detector",
        help="with --clip: z of the recorded mesh as the detector writes it, converted to frame pixels "
        "(Detectorv2: z x FaceRectWidth; MPDetector: z x FaceRectWidth / 256), or 'pixels': z already in pixels "
        "(a table rescaled after py-feat), as the ingest's data.mesh_units (default: %(default)s)",
    )
    add_force(p)
    p.set_defaults(func=_cmd_view)

    p = subparsers.add_parser(
        "animate",
        help="a video's AUs (or blendshapes, emotions) over time as an animated glTF (.glb): the release's rig "
        "with a morph-weight animation",
    )
    p.add_argument(
        "table",
        type=Path,
        help="py-feat's table of a video (CSV, .csv.gz or parquet; MPDetector or Detectorv2): one row per frame "
        "and face; frames without a face are bridged (interpolated up to 0.5 s, held beyond), of several faces "
        "in a frame the largest is used",
    )
    p.add_argument("--out", type=Path, required=True, help="the .glb to write (binary glTF 2.0)")
    p.add_argument(
        "--family",
        choices=("au", "blendshapes", "emotions"),
        default=None,
        help="what drives the rig: the table's AUs, its 52 MediaPipe blendshapes (morph targets with ARKit-style "
        "names) or its 7 emotions (either detector's names), read by name; the release must be that family's "
        "(default: the release's own family)",
    )
    p.add_argument(
        "--release",
        type=Path,
        default=None,
        help="release NPZ (default: release/au_to_mesh_pls.npz; with --family blendshapes "
        "releases/blendshapes/bs_to_mesh_pls.npz, with --family emotions releases/emotions/emotion_to_mesh_pls.npz)",
    )
    p.add_argument(
        "--video",
        default=None,
        help="the video to animate when the table holds several (py-feat's input path, or its stem where no other "
        "video has it, e.g. clip01 for videos/clip01.mp4; default: the table's only video)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="the video's frame rate; a frame's time is frame / fps (default: from approx_time where it tells, else 25)",
    )
    p.add_argument(
        "--pose",
        action="store_true",
        help="also turn the head by Pitch, Yaw, Roll (a rotation channel, Rotation.from_euler('xyz', ...)); "
        "default: off, the face stays pose-canonical",
    )
    p.add_argument(
        "--smooth",
        type=int,
        default=1,
        metavar="N",
        help="centred moving average over N frames (odd) against detector jitter (default: 1, no smoothing)",
    )
    add_force(p)
    p.set_defaults(func=_cmd_animate)

    from aumesh.export.dvc_plots import CONFIG_VALUE, TEMPLATE_FILE

    # A build step, not a user's command (`make tools` runs it after a change of package-lock.json): without help=,
    # argparse does not list it in `aumesh --help`.
    p = subparsers.add_parser(
        "dvc-plots-template",
        description="Write the HTML template for `dvc plots show` / `dvc plots diff` that draws offline "
        "(vega, vega-lite, vega-embed inlined from node_modules/).",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=TEMPLATE_FILE,
        help=f"the template file (default: %(default)s, named by .dvc/config as {CONFIG_VALUE})",
    )
    add_force(p)
    p.set_defaults(func=_cmd_dvc_plots_template)
