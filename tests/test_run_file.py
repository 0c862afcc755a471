"""Run files grow by appending: contents equal the concatenation of the frames, re-adding and
removing frames, out-of-order frames, damaged files rebuilt from the results, concurrent writers."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from service import run_file
from service.database import Database
from service.results import JobOutput
from service.store import ExposureRecord, Store

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def store(tmp_path: Path) -> Store:
    db = Database(tmp_path / "data" / "plenodust.sqlite")
    yield Store(tmp_path / "data", db)
    db.close()


def _columns(frame: int, n: int | None = None) -> dict[str, np.ndarray]:
    """A frame's particle table; sizes vary with the frame (0 included) so row ranges matter."""
    n = (frame * 7) % 5 if n is None else n
    rng = np.random.default_rng(frame)
    return {"index": np.arange(n), "x": rng.uniform(0, 480, n), "y": rng.uniform(0, 480, n),
            "alpha": rng.uniform(0.98, 1.02, n), "X": rng.normal(size=n), "Y": rng.normal(size=n),
            "Z": rng.normal(size=n), "brightness": rng.uniform(size=n)}


def _output(frame: int, n: int | None = None, **parameters) -> JobOutput:
    return JobOutput(columns=_columns(frame, n), parameters={"n_slices": 40, "frame_seen": frame, **parameters})


def _record(store: Store, frame: int, run: str = "r") -> ExposureRecord:
    """An exposure indexed at ``frame`` (register hands out frames in order)."""
    exposure_id = f"{frame:040x}"
    with store.db.write() as conn:
        record, _ = store.register(conn, exposure_id, run=run, kind="lfp", source="upload", serial=None)
    assert record.frame == frame
    return record


def _finish(store: Store, record: ExposureRecord, output: JobOutput) -> str:
    """What the runner does with a result: result file, run file, index."""
    store.write_result(record, output)
    how = store.update_run_file(record, output)
    with store.db.write() as conn:
        store.index_result(conn, record, output.particles)
    return how


def _expected(outputs: dict[int, JobOutput]) -> dict[str, np.ndarray]:
    """The concatenation of the frames' tables, by frame, with a frame column."""
    parts = [run_file.frame_rows(outputs[f].columns, f) for f in sorted(outputs)]
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def _assert_run(store: Store, outputs: dict[int, JobOutput], run: str = "r") -> None:
    got = store.read_run_columns(run)
    want = _expected(outputs)
    # Until its frame is linked (service.tracking) a row has no trajectory: particle -1, t and v NaN.
    particle = got.pop("particle")
    assert np.all((particle == -1) | np.isnan(particle))  # NaN in rows of a file from before trajectories
    for name in ("t", "vX", "vY", "vZ"):
        assert np.all(np.isnan(got.pop(name))), name
    assert list(got) == list(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    with h5py.File(store.run_path(run), "r") as f:
        coll = f["entry/exposures"]
        frames = sorted(outputs)
        assert coll.attrs["NX_class"] == "NXcollection"
        assert list(coll["frame"][()]) == frames
        assert [i.decode() for i in coll["id"][()]] == [f"{fr:040x}" for fr in frames]
        counts = [outputs[fr].particles for fr in frames]
        assert list(coll["particles"][()]) == counts
        assert list(coll["first_row"][()]) == list(np.concatenate([[0], np.cumsum(counts)[:-1]]))
        assert [json.loads(p)["frame_seen"] for p in coll["parameters"][()]] == frames
        assert json.loads(f["entry/process/parameters"][()])["frame_seen"] == frames[-1]


def test_frames_in_order_are_appended_in_place_and_equal_the_concatenation(store: Store) -> None:
    outputs = {}
    hows = []
    for frame in range(40):
        outputs[frame] = _output(frame)
        hows.append(_finish(store, _record(store, frame), outputs[frame]))
    assert hows[0] == "rewritten" and set(hows[1:]) == {"in place"}
    _assert_run(store, outputs)
    with h5py.File(store.run_path("r"), "r") as f:
        assert f.attrs["default"] == "entry" and f["entry"].attrs["NX_class"] == "NXentry"
        data = f["entry/data"]
        assert data.attrs["NX_class"] == "NXdata" and data.attrs["signal"] == "Z"
        assert data["Z"].attrs["units"] == "mm"
        assert all(data[name].maxshape == (None,) for name in json.loads(data.attrs["columns"]))
    assert not run_file.marker_path(store.run_path("r")).exists()


def test_a_frame_added_again_replaces_its_rows(store: Store) -> None:
    records = [_record(store, f) for f in range(6)]
    outputs = {f: _output(f, 3) for f in range(6)}
    for f in range(6):
        _finish(store, records[f], outputs[f])
    outputs[5] = _output(50, 4, frame_seen=5)  # the last frame again: a job re-run after a crash
    assert store.update_run_file(records[5], outputs[5]) == "in place"
    assert store.update_run_file(records[5], outputs[5]) == "in place"
    _assert_run(store, outputs)
    outputs[2] = _output(20, 1, frame_seen=2)  # an earlier frame again: later rows move
    store.update_run_file(records[2], outputs[2])
    store.update_run_file(records[2], outputs[2])
    _assert_run(store, outputs)


def test_a_frame_removed_leaves_the_others(store: Store) -> None:
    records = [_record(store, f) for f in range(5)]
    outputs = {f: _output(f, f + 1) for f in range(5)}
    for f in range(5):
        _finish(store, records[f], outputs[f])
    for f in (4, 1):  # the last, then one in the middle
        store.update_run_file(records[f], None)
        del outputs[f]
        _assert_run(store, outputs)
    assert store.update_run_file(records[1], None) == "in place"  # already gone: nothing changes
    _assert_run(store, outputs)
    outputs[4] = _output(4, 2)
    store.update_run_file(records[4], outputs[4])
    _assert_run(store, outputs)


def test_frames_out_of_order_end_up_sorted(store: Store) -> None:
    records = [_record(store, f) for f in range(8)]
    outputs = {}
    for f in (0, 2, 1, 5, 3, 4, 7, 6):
        outputs[f] = _output(f, 2 + f % 3)
        store.update_run_file(records[f], outputs[f])
        _assert_run(store, outputs)


def test_a_column_one_frame_lacks_is_nan_there(store: Store) -> None:
    records = [_record(store, f) for f in range(4)]
    outputs = {0: _output(0, 2), 1: _output(1, 2), 2: _output(2, 1), 3: _output(3, 2)}
    outputs[1].columns["extra"] = np.array([7.0, 8.0])
    outputs[2].columns["label"] = np.array(["a"])  # text cannot be NaN: a rewrite, not an error
    for f in range(4):
        store.update_run_file(records[f], outputs[f])
    cols = store.read_run_columns("r")
    np.testing.assert_array_equal(cols["extra"], [np.nan, np.nan, 7, 8, np.nan, np.nan, np.nan])
    assert list(cols) == ["index", "x", "y", "alpha", "X", "Y", "Z", "brightness", "frame", "particle", "t", "vX",
                          "vY", "vZ", "extra", "label"]
    np.testing.assert_array_equal(cols["frame"], [0, 0, 1, 1, 2, 3, 3])


def test_a_truncated_run_file_is_rebuilt_from_the_results(store: Store, caplog) -> None:
    outputs = {f: _output(f, 3) for f in range(6)}
    records = [_record(store, f) for f in range(7)]
    for f in range(6):
        _finish(store, records[f], outputs[f])
    path = store.run_path("r")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    outputs[6] = _output(6, 2)
    with caplog.at_level(logging.WARNING):
        assert _finish(store, records[6], outputs[6]) == "rebuilt"
    assert "rebuilding it from the per-exposure result files" in caplog.text
    _assert_run(store, outputs)
    assert _finish(store, records[6], outputs[6]) == "in place"  # and appending again afterwards


def test_a_file_left_half_written_is_rebuilt_before_it_is_read(store: Store, caplog) -> None:
    outputs = {f: _output(f, 4) for f in range(5)}
    for f in range(5):
        _finish(store, _record(store, f), outputs[f])
    path = store.run_path("r")
    # What a kill mid-append leaves: the marker, and bytes that may or may not be consistent.
    run_file.marker_path(path).touch()
    with h5py.File(path, "r+") as f:
        f["entry/data/Z"].resize((3,))
    with caplog.at_level(logging.WARNING):
        _assert_run(store, outputs)
    assert "half-written" in caplog.text and not run_file.marker_path(path).exists()
    # Bookkeeping that disagrees without a marker is caught too.
    with h5py.File(path, "r+") as f:
        f["entry/exposures/particles"][0] = 9
    assert store.read_run_columns("r") is not None
    _assert_run(store, outputs)


def test_a_deleted_run_file_comes_back_with_every_result(store: Store) -> None:
    outputs = {f: _output(f, 2) for f in range(3)}
    records = [_record(store, f) for f in range(4)]
    for f in range(3):
        _finish(store, records[f], outputs[f])
    store.run_path("r").unlink()
    outputs[3] = _output(3, 2)
    assert _finish(store, records[3], outputs[3]) == "rebuilt"
    _assert_run(store, outputs)


def test_a_run_file_in_the_older_fixed_size_layout_is_rewritten_then_appended(store: Store) -> None:
    records = [_record(store, f) for f in range(3)]
    outputs = {0: _output(0, 2), 1: _output(1, 3)}
    table = _expected(outputs)
    # The layout written before appending: contiguous datasets and no first_row.
    with h5py.File(store.run_path("r"), "w") as f:
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        data = entry.create_group("data")
        data.attrs["columns"] = json.dumps(list(table))
        for name, column in table.items():
            data.create_dataset(name, data=column)
        entry.create_group("process")["parameters"] = "{}"
        coll = entry.create_group("exposures")
        coll["id"] = np.array([f"{f:040x}" for f in (0, 1)], dtype="S40")
        coll["frame"] = np.array([0, 1])
        coll["particles"] = np.array([2, 3])
        coll.create_dataset("parameters", data=[json.dumps(outputs[f].parameters) for f in (0, 1)],
                            dtype=h5py.string_dtype())
    outputs[2] = _output(2, 4)
    assert store.update_run_file(records[2], outputs[2]) == "rewritten"
    _assert_run(store, outputs)
    outputs[2] = _output(2, 1, frame_seen=2)
    assert store.update_run_file(records[2], outputs[2]) == "in place"
    _assert_run(store, outputs)


def test_a_reader_holding_the_file_open_gets_its_old_file_and_the_update_still_lands(store: Store) -> None:
    records = [_record(store, f) for f in range(3)]
    outputs = {0: _output(0, 2), 1: _output(1, 3)}
    for f in (0, 1):
        store.update_run_file(records[f], outputs[f])
    reader = subprocess.Popen(
        [sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r'); print(len(f['entry/data/Z']),"
         " flush=True); sys.stdin.readline(); print(len(f['entry/data/Z']), f['entry/data/Z'][-1], flush=True)",
         str(store.run_path("r"))], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout.readline().split() == ["5"]
        outputs[2] = _output(2, 4)
        assert store.update_run_file(records[2], outputs[2]) == "rewritten"  # renamed, not changed under it
        reader.stdin.write("\n")
        reader.stdin.flush()
        assert reader.stdout.readline().split() == ["5", str(outputs[1].columns["Z"][-1])]
    finally:
        reader.kill()
        reader.wait()
    _assert_run(store, outputs)
    outputs[3] = _output(3, 1)
    assert store.update_run_file(_record(store, 3), outputs[3]) == "in place"


def test_concurrent_writers_and_readers_keep_the_file_whole(store: Store, tmp_path: Path) -> None:
    # Two Store objects on one folder stand for two processes: only the flock keeps them apart.
    other = Store(store.data_dir, store.db)
    records = [_record(store, f) for f in range(48)]
    outputs = {f: _output(f) for f in range(48)}
    errors: list[BaseException] = []
    done = threading.Event()

    def write(frames: range, target: Store) -> None:
        try:
            for f in frames:
                target.update_run_file(records[f], outputs[f])
        except BaseException as exc:  # reported below
            errors.append(exc)

    def read() -> None:
        try:
            while not done.is_set():
                cols = other.read_run_columns("r")
                if cols is not None:
                    assert np.all(np.diff(cols["frame"]) >= 0)
                    for f in np.unique(cols["frame"]):
                        np.testing.assert_array_equal(cols["Z"][cols["frame"] == f], outputs[f].columns["Z"])
        except BaseException as exc:
            errors.append(exc)

    writers = [threading.Thread(target=write, args=(range(k, 48, 4), store if k % 2 else other))
               for k in range(4)]
    reader = threading.Thread(target=read)
    reader.start()
    for t in writers:
        t.start()
    for t in writers:
        t.join()
    done.set()
    reader.join()
    assert not errors, errors
    _assert_run(store, {f: o for f, o in outputs.items()})


_WRITER = textwrap.dedent("""
    import sys
    from pathlib import Path
    import numpy as np
    from service.database import Database
    from service.results import JobOutput
    from service.store import Store
    data = Path(sys.argv[1])
    db = Database(data / "plenodust.sqlite")
    store = Store(data, db)
    print("ready", flush=True)
    for frame in range(100000):
        exposure_id = f"{frame:040x}"
        with db.write() as conn:
            record, _ = store.register(conn, exposure_id, run="k", kind="lfp", source="upload", serial=None)
        rng = np.random.default_rng(frame)
        n = 2000 + frame % 7
        output = JobOutput(columns={"Z": rng.normal(size=n), "X": rng.normal(size=n)}, parameters={"f": frame})
        store.write_result(record, output)
        store.update_run_file(record, output)
        with db.write() as conn:
            store.index_result(conn, record, n)
""")


@pytest.mark.slow  # two processes
@pytest.mark.parametrize("delay_s", [0.7, 1.1])
def test_a_writer_killed_mid_run_loses_nothing(tmp_path: Path, delay_s: float) -> None:
    data = tmp_path / "data"
    data.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    child = subprocess.Popen([sys.executable, "-c", _WRITER, str(data)], stdout=subprocess.PIPE, text=True,
                             env=env, cwd=ROOT)
    assert child.stdout.readline().strip() == "ready"
    time.sleep(delay_s)
    child.send_signal(signal.SIGKILL)
    child.wait()
    db = Database(data / "plenodust.sqlite")
    try:
        store = Store(data, db)
        indexed = [r["frame"] for r in db.read("SELECT frame FROM results WHERE run = 'k' ORDER BY frame")]
        assert indexed, "the writer wrote nothing before it was killed; give it longer"
        cols = store.read_run_columns("k")
        frames = sorted(set(cols["frame"].tolist()))
        # Every indexed frame is there; at most the one being stored when killed besides.
        assert frames[: len(indexed)] == indexed and len(frames) <= len(indexed) + 1
        for frame in frames:
            want = store.read_columns(f"{frame:040x}")
            np.testing.assert_array_equal(cols["Z"][cols["frame"] == frame], want["Z"])
        # And the next frame goes on from there.
        with db.write() as conn:
            record, _ = store.register(conn, "f" * 40, run="k", kind="lfp", source="upload", serial=None)
        store.update_run_file(record, JobOutput(columns={"Z": np.ones(3), "X": np.zeros(3)}, parameters={}))
        assert list(store.read_run_columns("k")["frame"][-3:]) == [record.frame] * 3
    finally:
        db.close()


def test_a_snapshot_is_a_whole_copy_that_later_appends_leave_alone(store: Store) -> None:
    assert store.run_file_snapshot("r") is None
    records = [_record(store, f) for f in range(4)]
    outputs = {f: _output(f, 3) for f in range(3)}
    for f in range(3):
        _finish(store, records[f], outputs[f])
    copy = store.run_file_snapshot("r")
    try:
        assert copy.parent == store.cache_dir
        store.update_run_file(records[3], _output(3, 5))
        with h5py.File(copy, "r") as f:
            np.testing.assert_array_equal(f["entry/data/Z"][()], _expected(outputs)["Z"])
            assert list(f["entry/exposures/frame"][()]) == [0, 1, 2]
    finally:
        copy.unlink()


def test_a_file_held_open_in_this_process_is_replaced_not_changed_under_the_reader(store: Store) -> None:
    records = [_record(store, f) for f in range(3)]
    outputs = {0: _output(0, 2), 1: _output(1, 3)}
    for f in (0, 1):
        store.update_run_file(records[f], outputs[f])
    with h5py.File(store.run_path("r"), "r") as held:  # HDF5 refuses a second, writing open here
        outputs[2] = _output(2, 4)
        assert store.update_run_file(records[2], outputs[2]) == "rewritten"
        assert held["entry/data/Z"].shape == (5,)
    _assert_run(store, outputs)
