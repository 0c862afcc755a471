"""One particle-table I/O for the CLI, the service's files and its downloads."""

from __future__ import annotations

import io
import json
import math

import h5py
import numpy as np
import pytest

from analysis.errors import ParameterError
from analysis.formats.particle_table import (combine, csv_text, nx_entry, nx_group, read_csv, read_hdf5_columns,
                                             read_nx_columns, read_table, set_nx_parameters, table_h5_bytes,
                                             write_csv, write_hdf5, write_nx_columns, write_nx_process)

TABLE = {"index": np.array([0, 1, 2]), "x": np.array([1.5, np.nan, 3.0]), "Z": np.array([60.1, 59.9, 1 / 3])}


def test_csv_has_lf_line_endings_full_precision_and_empty_nan(tmp_path):
    text = csv_text(TABLE)
    assert "\r" not in text and text.count("\n") == 4
    assert text.splitlines()[2] == "1,,59.9" and repr(1 / 3) in text
    path = write_csv(TABLE, tmp_path / "t.csv")
    assert path.read_bytes() == text.encode()
    back = read_csv(path)
    assert back["index"].dtype == np.int64 and math.isnan(back["x"][1]) and back["Z"][2] == 1 / 3


def test_csv_that_is_no_table_says_so(tmp_path):
    (tmp_path / "bad.csv").write_text("particle,Z\n0,abc\n")
    with pytest.raises(ParameterError, match="not a particle table"):
        read_csv(tmp_path / "bad.csv")


def test_nexus_columns_round_trip_with_text_units_and_signal():
    columns = dict(TABLE, camera=np.array(["A1", "B2", "C3"]))
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        data = nx_group(nx_entry(f, title="t"), "data", "NXdata")
        write_nx_columns(data, columns, chunk_rows=16)
        assert data.attrs["signal"] == "Z" and data["Z"].attrs["units"] == "mm" and data["Z"].maxshape == (None,)
        back = read_nx_columns(data)
        assert list(back) == list(columns) and back["camera"].tolist() == ["A1", "B2", "C3"]
        assert read_nx_columns(data, start=2)["index"].tolist() == [2]


def test_parameters_as_json_and_attributes_replaced_when_they_change():
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        process = write_nx_process(nx_entry(f, title="t"), {"n_slices": 40, "depth_range_mm": None, "grid": [1, 2]})
        assert process.attrs["n_slices"] == 40 and process.attrs["depth_range_mm"] == "none"
        assert json.loads(process["parameters"][()])["grid"] == [1, 2]
        set_nx_parameters(process, {"n_slices": 20})
        assert process.attrs["n_slices"] == 20 and "depth_range_mm" not in process.attrs
        assert json.loads(process["parameters"][()]) == {"n_slices": 20}


def test_a_download_and_a_batch_file_hold_the_same_table(tmp_path):
    batch = combine([TABLE, TABLE])
    assert batch["frame"].tolist() == [0, 0, 0, 1, 1, 1] and list(batch)[0] == "frame"
    path = write_hdf5(tmp_path / "b.h5", batch, parameters={"n_slices": 3},
                      frames=[{"metadata": {"name": "a"}, "curves": np.ones((3, 4)), "stack": None}] * 2)
    with h5py.File(path) as f:
        assert json.loads(f["entry/frames/1"].attrs["metadata"]) == {"name": "a"}
        assert f["entry/frames/0/curves"].shape == (3, 4) and "stack" not in f["entry/frames/0"]
    download = tmp_path / "d.h5"
    download.write_bytes(table_h5_bytes(batch, title="run"))
    for name in batch:
        np.testing.assert_array_equal(read_hdf5_columns(download)[name], read_hdf5_columns(path)[name])
    assert read_table(path, frame=1, required=("Z",))["index"].tolist() == [0, 1, 2]
    with pytest.raises(ParameterError, match="no column"):
        read_table(path, required=("vX",))


def test_a_table_from_before_the_rename_reads_its_row_number_as_index(tmp_path):
    # Until trajectories came, `particle` numbered an exposure's rows; it now means a trajectory id.
    old = write_csv({"particle": np.array([0, 1]), "X": np.array([1.0, 2.0]), "Z": np.array([60.0, 61.0])},
                    tmp_path / "old.csv")
    back = read_csv(old)
    assert list(back) == ["index", "X", "Z"] and back["index"].tolist() == [0, 1]
    # A linked table (with t) keeps its particle column: the trajectory ids.
    linked = write_csv({"frame": np.array([0, 1]), "t": np.array([0.0, 1.0]), "particle": np.array([7, 7]),
                        "X": np.array([1.0, 1.1])}, tmp_path / "linked.csv")
    assert read_csv(linked)["particle"].tolist() == [7, 7]
