"""A CSV that is not what py-feat writes is named for what it is, with its file and line (a text editor's count: the
header is line 1): a byte-order mark is accepted; ``;`` or tab separators, decimal commas, a file cut mid-row, NUL
bytes, text or NaN in a face row's AUs, pose or mesh are one-line errors. And py-feat's one CSV per video reads as
the same rows in one CSV would: one header and layout for all, their rows parsed and written together.

The references are the file's own text (the line a value was written on) and the same rows read another way (the
CSV without its BOM, the rows as one CSV)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from aumesh.core.errors import TableError, UserError
from aumesh.data import ingest as ingest_data
from aumesh.data import readers
from aumesh.pipeline import ingest
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec

SPEC = SynthSpec(n_frames=40, n_videos=5, seed=1, identity_scale=0.0)
NPY = "{stem}_mesh.npy"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(one CSV of SPEC's videos, the same videos as one CSV each): every row a face row (no-face and background
    faces off, so each line's row is kept)."""
    root = tmp_path_factory.mktemp("csv_messages")
    kw = dict(no_face_rate=0.0, extra_face_rate=0.0)
    write_pyfeat_tables(root / "one", SPEC, videos_per_file=None, **kw)
    write_pyfeat_tables(root / "per_video", SPEC, videos_per_file=1, **kw)
    return root / "one" / "clip_0000.csv", root / "per_video"


def _ingest(folder: Path, out: Path, range_bytes: int | None = None) -> ingest_data.Counts:
    """The ingest's read and clean of every source under ``folder`` into one table ``out`` (ranges of
    ``range_bytes``)."""
    sources = ingest.find_sources(folder, "**/*", NPY)
    spans = [s for src in sources for s in readers.csv_spans(src, *([range_bytes] if range_bytes else []))]
    return ingest_data.write_clean(spans, out, "largest", None)


def _copy(text: bytes, tmp_path: Path, name: str = "clip.csv") -> Path:
    folder = tmp_path / "data"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(text)
    return folder


def _set_field(text: bytes, line: int, column: str, value: str) -> bytes:
    """``text`` with ``column`` of line ``line`` (1-based, header = 1) written as ``value``."""
    lines = text.split(b"\n")
    k = lines[0].decode().split(",").index(column)
    fields = lines[line - 1].split(b",")
    fields[k] = value.encode()
    lines[line - 1] = b",".join(fields)
    return b"\n".join(lines)


def test_bom_is_accepted(made, tmp_path):
    """Excel's BOM before the first column's name (here py-feat's ``input``, moved first) is no part of the name."""
    one, _ = made
    df = pd.read_csv(one)
    text = df[["input", *(c for c in df.columns if c != "input")]].to_csv(index=False).encode()
    plain = _ingest(_copy(text, tmp_path / "a"), tmp_path / "a.parquet")
    bom = _ingest(_copy(b"\xef\xbb\xbf" + text, tmp_path / "b"), tmp_path / "b.parquet")
    assert readers.csv_header(tmp_path / "b" / "data" / "clip.csv")[0] == "input"
    assert bom.rows_out == plain.rows_out == text.count(b"\n") - 1
    assert pq.read_table(tmp_path / "b.parquet").equals(pq.read_table(tmp_path / "a.parquet"))


@pytest.mark.parametrize(("sep", "decimal", "said"), [(";", ",", "';'"), ("\t", ".", "tab")])
def test_other_separators_named_on_line_1(made, tmp_path, sep, decimal, said):
    one, _ = made
    path = tmp_path / "data" / "clip.csv"
    path.parent.mkdir()
    pd.read_csv(one).to_csv(path, sep=sep, decimal=decimal, index=False)
    with pytest.raises(TableError) as err:
        _ingest(path.parent, tmp_path / "out.parquet")
    message = str(err.value)
    assert str(path) in message and "line 1" in message and f"separated by {said}" in message
    assert ("decimal commas" in message) == (decimal == ",")
    assert "\n" not in message


def test_decimal_comma_named_with_its_line(made, tmp_path):
    one, _ = made
    text = _set_field(one.read_bytes(), 9, "AU12", '"0,5"')
    with pytest.raises(TableError, match=r"column 'AU12' holds '0,5' at line 9: a decimal comma"):
        _ingest(_copy(text, tmp_path), tmp_path / "out.parquet")


def test_text_value_named_with_its_line(made, tmp_path):
    one, _ = made
    text = _set_field(one.read_bytes(), 7, "Pitch", "abc")
    with pytest.raises(TableError, match=r"clip\.csv: column 'Pitch' holds 'abc' at line 7, not a number"):
        _ingest(_copy(text, tmp_path), tmp_path / "out.parquet")


def test_file_cut_mid_row(made, tmp_path):
    one, _ = made
    text = one.read_bytes()
    cut = text[: len(text) - len(text.split(b"\n")[-2]) // 2]  # half of the last row left, no line end
    last = cut.count(b"\n") + 1
    with pytest.raises(TableError, match=rf"ends mid-row: line {last} has \d+ of the header's \d+ fields"):
        _ingest(_copy(cut, tmp_path), tmp_path / "out.parquet")


@pytest.mark.parametrize("where", ["end", "middle"])
def test_nul_bytes_named_with_their_line(made, tmp_path, where):
    one, _ = made
    text = one.read_bytes()
    if where == "end":
        bad, line = text + b"\0" * 4096, text.count(b"\n") + 1
    else:
        at = len(b"\n".join(text.split(b"\n")[:10])) + 5  # 5 bytes into line 11
        bad, line = text[:at] + b"\0" * 64 + text[at + 64 :], 11
    with pytest.raises(TableError, match=rf"clip\.csv: NUL bytes from line {line} "):
        _ingest(_copy(bad, tmp_path), tmp_path / "out.parquet")


@pytest.mark.parametrize(
    ("column", "value", "said"),
    [("AU12", "n/a", "'AU12' has 1 NaN/inf"), ("Yaw", "", "'Yaw' has 1 NaN/inf"), ("x_5", "", "mesh column x_5")],
)
def test_missing_face_values_name_the_csv_line(made, tmp_path, column, value, said):
    """Found by the ingest in the user's CSV, at its line (never first by prepare in an ingested table); the line is
    right in a later byte range of the file (ranges of ~3 rows here)."""
    one, _ = made
    text = one.read_bytes()
    line = text.count(b"\n") - 2  # in the last ranges
    bad = _set_field(text, line, column, value)
    with pytest.raises(TableError) as err:
        _ingest(_copy(bad, tmp_path), tmp_path / "out.parquet", range_bytes=3 * len(text.split(b"\n")[1]))
    message = str(err.value)
    assert "clip.csv" in message and said in message and f"line {line}" in message, message


def test_per_video_csvs_read_as_one(made, tmp_path):
    """One header tuple and one Layout for all the files; their rows parsed together and written as one row group:
    the same table as the one CSV's."""
    one, per_video = made
    sources = ingest.find_sources(per_video, "**/*", NPY)
    assert len(sources) == SPEC.n_videos
    assert all(s.header is sources[0].header and s.layout is sources[0].layout for s in sources)
    many = _ingest(per_video, tmp_path / "many.parquet")
    single = _ingest(one.parent, tmp_path / "one.parquet")
    assert pq.read_table(tmp_path / "many.parquet").equals(pq.read_table(tmp_path / "one.parquet"))
    assert pq.ParquetFile(tmp_path / "many.parquet").metadata.num_row_groups == 1
    per_source = {"identity_labels"}  # summed over sources: each file's own labels
    assert {k: v for k, v in many.as_dict().items() if k not in per_source} == {
        k: v for k, v in single.as_dict().items() if k not in per_source
    }
    assert sorted(many.units) == sorted(str(s.path) for s in sources)  # each source's units still its own


def test_error_in_one_of_many_small_csvs_names_that_file(made, tmp_path):
    """The joined read of small files falls back to one file at a time when one is refused: the error names it."""
    _, per_video = made
    folder = tmp_path / "data"
    shutil.copytree(per_video, folder)
    bad = sorted(folder.glob("*.csv"))[2]
    bad.write_bytes(_set_field(bad.read_bytes(), 4, "AU04", "oops"))
    with pytest.raises(TableError, match=rf"{bad.name}: column 'AU04' holds 'oops' at line 4"):
        _ingest(folder, tmp_path / "out.parquet")


def test_bom_in_a_parquet_column_name(made, tmp_path):
    one, _ = made
    df = pd.read_csv(one).rename(columns={"input": "\ufeffinput"})
    folder = tmp_path / "data"
    folder.mkdir()
    df[[c for c in df.columns if not c.startswith(("x_", "y_", "z_"))]].to_parquet(folder / "clip.parquet")
    np.save(folder / "clip_mesh.npy", np.zeros((len(df), 478, 3), np.float32))
    with pytest.raises(TableError, match=r"starts with a byte-order mark .*encoding='utf-8-sig'"):
        ingest.find_sources(folder, "**/*", NPY)


def test_predict_reads_the_header_as_ingest_does(made, tmp_path):
    """``aumesh predict``'s table reader: the same header checks (a BOM accepted, ';' named)."""
    from aumesh.pipeline import predict

    one, _ = made
    df = pd.read_csv(one)
    path = tmp_path / "fex.csv"
    path.write_bytes(b"\xef\xbb\xbf" + df.to_csv(index=False).encode())
    assert predict.table_header(path) == list(df.columns)
    df.to_csv(path, sep=";", decimal=",", index=False)
    with pytest.raises(UserError, match=r"^\S*fex\.csv: line 1 \(the header\) is separated by ';'"):
        predict.table_header(path)


def test_files_too_short_to_judge_alone_have_their_units_judged_together(made, tmp_path):
    """py-feat's one CSV per short video: a file of a few faces is not refused for its own faces' proportions (one or
    two faces are a single draw of depth/height) but judged with the others of its detector and units; a folder of
    flat faces is still refused, naming the files judged together."""
    from conftest import default_config

    _, per_video = made
    data = tmp_path / "data"
    shutil.copytree(per_video, data)
    files = sorted(data.glob("*.csv"))
    df = pd.read_csv(files[0])
    z = [c for c in df.columns if c.startswith("z_")]
    assert len(z) == 478 and len(df) < ingest.UNIT_CHECK_ROWS
    df[z] *= 0.01  # this video's faces alone: depth/height ~0.005, a flat face
    df.to_csv(files[0], index=False)
    alone = _ingest(data, tmp_path / "all.parquet").units[str(files[0])]
    with pytest.raises(TableError, match="proportions"):  # judged alone, as the guard judged every file before
        ingest.check_units(str(files[0]), "MPDetector", alone, "detector")
    manifest = ingest.run(default_config(**{"paths.data_dir": str(data)}), tmp_path / "ingested")
    assert manifest["counts"]["frames_out"] == SPEC.n_frames  # every video kept, the flat one among them
    for path in files[1:]:  # every video flat: refused, the files named as judged together
        df = pd.read_csv(path)
        df[z] *= 0.01
        df.to_csv(path, index=False)
    with pytest.raises(TableError) as err:
        ingest.run(default_config(**{"paths.data_dir": str(data)}), tmp_path / "flat")
    message = str(err.value)
    assert message.startswith(f"{len(files)} files of fewer than {ingest.UNIT_CHECK_ROWS} face rows each (")
    assert "judged together: the faces do not have a face's proportions" in message
