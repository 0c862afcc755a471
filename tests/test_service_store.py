"""Storage: atomic writes, the NeXus layout of run files, idempotent updates."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from analysis.formats.atomic_write import atomic_path, write_atomic
from service.database import Database, DatabaseClosed
from service.results import JobOutput
from service.store import Store


@pytest.fixture
def store(tmp_path: Path) -> Store:
    db = Database(tmp_path / "data" / "plenodust.sqlite")
    yield Store(tmp_path / "data", db)
    db.close()


def _output(n: int, z0: float) -> JobOutput:
    return JobOutput(columns={"index": np.arange(n), "x": np.linspace(1, 2, n), "y": np.linspace(3, 4, n),
                              "alpha": np.full(n, 1.0), "X": np.arange(n) * 0.1, "Y": np.arange(n) * 0.2,
                              "Z": z0 + np.arange(n), "brightness": np.full(n, 5.0)},
                     parameters={"n_slices": 40, "alpha_min": 0.987},
                     curves=np.ones((n, 3), np.float32), curve_alpha=np.array([0.99, 1.0, 1.01]),
                     slices=np.full((2, 4, 5), 7, np.uint8), slice_alpha=np.array([0.99, 1.01]))


def _record(store: Store, exposure_id: str, run: str):
    with store.db.write() as conn:
        record, created = store.register(conn, exposure_id, run=run, kind="lfp", source="upload", serial=None)
    return record


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path: Path) -> None:
    target = tmp_path / "f.bin"
    write_atomic(target, b"old")

    with pytest.raises(OSError), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise OSError("disk full")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]  # no temporary left behind


def test_raw_exposures_are_stored_by_sha1_once(store: Store) -> None:
    assert store.put_raw("ab" + "0" * 38, {".lfp": b"bytes"}) == "lfp"
    [path] = store.raw_paths("ab" + "0" * 38, "lfp")
    assert path == store.raw_dir / "ab" / f"ab{'0' * 38}.lfp" and path.read_bytes() == b"bytes"
    assert store.put_raw("cd" + "0" * 38, {".RAW": b"r", ".TXT": b"t"}) == "raw"
    assert [p.read_bytes() for p in store.raw_paths("cd" + "0" * 38, "raw")] == [b"r", b"t"]


def test_same_exposure_registers_once_and_frames_count_per_run(store: Store) -> None:
    a = _record(store, "a" * 40, "r1")
    b = _record(store, "b" * 40, "r1")
    c = _record(store, "c" * 40, "r2")
    with store.db.write() as conn:
        again, created = store.register(conn, "a" * 40, run="other", kind="lfp", source="upload", serial=None)
    assert (a.frame, b.frame, c.frame) == (0, 1, 0)
    assert not created and again.run == "r1" and again.frame == 0


def test_run_file_is_nexus_with_a_frame_column_and_parameters(store: Store) -> None:
    a, b = _record(store, "a" * 40, "run1"), _record(store, "b" * 40, "run1")
    store.update_run_file(b, _output(2, 50.0))
    store.update_run_file(a, _output(3, 60.0))
    with h5py.File(store.run_path("run1"), "r") as f:
        assert f.attrs["default"] == "entry"
        assert f["entry"].attrs["NX_class"] == "NXentry"
        data = f["entry/data"]
        assert data.attrs["NX_class"] == "NXdata" and data.attrs["signal"] == "Z"
        for name in ("x", "y", "alpha", "X", "Y", "Z", "brightness", "frame"):
            assert data[name].shape == (5,)
        assert data["Z"].attrs["units"] == "mm"
        np.testing.assert_array_equal(data["frame"][()], [0, 0, 0, 1, 1])  # ordered by frame
        np.testing.assert_array_equal(data["Z"][()], [60, 61, 62, 50, 51])
        assert f["entry/process"].attrs["NX_class"] == "NXprocess"
        assert json.loads(f["entry/process/parameters"][()])["n_slices"] == 40
        assert [i.decode() for i in f["entry/exposures/id"][()]] == ["a" * 40, "b" * 40]


def test_run_file_update_is_idempotent_and_removable(store: Store) -> None:
    a, b = _record(store, "a" * 40, "r"), _record(store, "b" * 40, "r")
    store.update_run_file(a, _output(3, 60.0))
    store.update_run_file(b, _output(2, 50.0))
    store.update_run_file(a, _output(3, 70.0))  # the job ran again after a crash
    cols = store.read_run_columns("r")
    assert list(cols["frame"]) == [0, 0, 0, 1, 1]
    np.testing.assert_array_equal(cols["Z"], [70, 71, 72, 50, 51])
    store.update_run_file(a, None)
    assert list(store.read_run_columns("r")["frame"]) == [1, 1]


def test_result_file_round_trips_table_curves_and_slices(store: Store) -> None:
    a = _record(store, "a" * 40, "r")
    out = _output(3, 60.0)
    store.write_result(a, out)
    cols = store.read_columns(a.id)
    assert list(cols) == list(out.columns)
    np.testing.assert_array_equal(cols["Z"], out.columns["Z"])
    alpha, brightness = store.read_curves(a.id)
    assert brightness.shape == (3, 3) and alpha.tolist() == [0.99, 1.0, 1.01]
    assert store.slice_count(a.id) == 2
    assert store.read_slice(a.id, 1)[0] == 1.01 and store.read_slice(a.id, 2) is None
    assert store.read_parameters(a.id)["alpha_min"] == 0.987
    assert store.read_rejected(a.id) == {}
    out.rejected = {"x": np.array([5.0]), "alpha": np.array([1.02]), "reason": np.array(["extended"])}
    store.write_result(a, out)
    rejected = store.read_rejected(a.id)
    assert rejected["reason"].tolist() == ["extended"] and rejected["alpha"].tolist() == [1.02]


def test_nan_columns_where_one_frame_lacks_a_column(store: Store) -> None:
    a, b = _record(store, "a" * 40, "r"), _record(store, "b" * 40, "r")
    first = _output(1, 1.0)
    second = _output(1, 2.0)
    second.columns["extra"] = np.array([9.0])
    store.update_run_file(a, first)
    store.update_run_file(b, second)
    extra = store.read_run_columns("r")["extra"]
    assert np.isnan(extra[0]) and extra[1] == 9.0


def test_closing_waits_for_a_write_under_way_and_then_refuses_more(tmp_path: Path) -> None:
    """A thread still writing when the service stops (a cancelled task's) finishes its transaction
    before the connections close; closing them under it crashed the service (SQLite segfault)."""
    import threading
    import time

    db = Database(tmp_path / "index.sqlite")
    inside = threading.Event()
    errors: list[BaseException] = []

    def slow_write() -> None:
        try:
            with db.write() as conn:
                inside.set()
                time.sleep(0.3)
                conn.execute("INSERT INTO settings_kv (key, value) VALUES ('last', 'written')")
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    writer = threading.Thread(target=slow_write)
    writer.start()
    assert inside.wait(10)
    db.close()
    writer.join()
    assert errors == []
    assert Database(tmp_path / "index.sqlite").get_value("last") == "written"
    with pytest.raises(DatabaseClosed, match="closed"):
        db.get_value("last")

