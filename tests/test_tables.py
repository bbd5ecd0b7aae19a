"""Every bubsub table is written one way: six significant digits, empty cells for unknowns, a CSVW sidecar."""

import csv
import json

import numpy as np
import pytest

from bubsub.core.io.tables import SIGNIFICANT_DIGITS, csv_metadata_path, format_cell, write_table

INFO = {"id": ("", "row id"), "volume_mm3": ("mm^3", "a volume"), "count": ("1", "a count"),
        "label": ("", "a word")}


def test_write_table_rounds_blanks_unknowns_and_describes_every_column(tmp_path):
    rows = [{"id": 1, "volume_mm3": 1 / 3, "count": np.int64(4), "label": "a"},
            {"id": 2, "volume_mm3": float("nan"), "count": 0, "label": "b"},
            {"id": 3, "volume_mm3": None, "count": 2, "label": ""},
            {"id": 4, "volume_mm3": np.float32(1234567.0), "count": 1, "label": "c"}]
    files = write_table(tmp_path / "t.csv", rows, INFO, title="a table")
    assert files == [tmp_path / "t.csv", tmp_path / "t.csv-metadata.json"]
    text = (tmp_path / "t.csv").read_text()
    assert "nan" not in text.lower() and text.splitlines()[0] == "id,volume_mm3,count,label"
    with open(tmp_path / "t.csv", newline="") as fh:
        back = list(csv.DictReader(fh))
    assert [r["volume_mm3"] for r in back] == ["0.333333", "", "", "1.23457e+06"]
    assert [int(r["count"]) for r in back] == [4, 0, 2, 1]
    meta = json.loads(csv_metadata_path(tmp_path / "t.csv").read_text())
    assert meta["null"] == "" and f"{SIGNIFICANT_DIGITS} significant digits" in meta["dc:description"]
    cols = {c["name"]: c for c in meta["tableSchema"]["columns"]}
    assert list(cols) == list(INFO) and cols["volume_mm3"]["unit"] == "mm^3"
    assert (cols["id"]["datatype"], cols["volume_mm3"]["datatype"], cols["label"]["datatype"]) == \
        ("integer", "number", "string")


def test_an_undescribed_or_missing_column_writes_nothing(tmp_path):
    with pytest.raises(ValueError, match="keys differ"):
        write_table(tmp_path / "t.csv", [{"id": 1}], INFO, title="t")
    assert list(tmp_path.iterdir()) == []


def test_format_cell():
    assert format_cell(float("nan")) == "" and format_cell(None) == ""
    assert format_cell(2.0) == "2" and format_cell(-0.000123456789) == "-0.000123457"
    assert format_cell(float("inf")) == "inf" and format_cell(np.int32(7)) == 7 and format_cell(True) == "True"
    assert float(format_cell(np.pi, 10)) == pytest.approx(np.pi, rel=1e-9)


def _unindented(text):
    return "\n".join(line.strip() for line in text.splitlines())


def test_the_docs_list_every_column_of_the_analysis_and_track_tables():
    from pathlib import Path

    from bubsub.clients.analysis.folders import TABLE_FILES
    from bubsub.clients.pipeline.dynamic4d.outputs4d import tracks_info
    from bubsub.core.analysis.columns import describe, dynamics_columns
    from bubsub.core.analysis.snapshot import SNAPSHOT_TABLES
    from bubsub.core.io.tables import markdown_columns

    docs = Path(__file__).resolve().parents[1] / "docs"
    analysis, dynamic = (_unindented((docs / n).read_text()) for n in ("analysis.md", "dynamic.md"))
    tables = {**SNAPSHOT_TABLES, **{k: describe(v) for k, v in dynamics_columns("s").items()}}
    assert set(tables) == set(TABLE_FILES)
    for name, info in tables.items():
        assert _unindented(markdown_columns(info)) in analysis, f"docs/analysis.md: the columns of {name}"
    assert _unindented(markdown_columns(tracks_info("s"))) in dynamic, "docs/dynamic.md: the columns of tracks.csv"
