"""`plenodust simulate` followed by `plenodust process` and `plenodust validate-plane`."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest

from analysis.simulation.scoring import score
from analysis.formats.particle_table import COLUMNS, read_csv
from service.cli.main import main
from analysis.formats.particle_table import csv_text as table_csv
from simulated_case import mean_nn_mm

SIZE = 900


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--scenario", "tilted-layer", "--seed", "5", "--size", str(SIZE), "--count", "2",
                 "--out", str(folder), "--quiet"]) == 0
    return folder


def run_json(capsys, argv):
    code = main(argv)
    out = capsys.readouterr()
    return code, (json.loads(out.out) if out.out.strip() else None), out.err


def test_process_one_exposure_to_csv(sim, tmp_path, capsys):
    out = tmp_path / "particles.csv"
    code, summary, err = run_json(capsys, ["process", str(sim / "IMG_0001.lfp"), "--calibration", str(sim / "calibration"),
                                           "--out", str(out), "--cache", str(tmp_path / "cache")])
    assert code == 0
    # Off a terminal it still says what it does: the kernels first, then each stage by name.
    assert "loading the analysis kernels" in err
    assert "IMG_0001.lfp (1/1): refocus" in err and "IMG_0001.lfp (1/1): refine" in err, err
    table = read_csv(out)
    assert list(table)[:8] == ["index", "x", "y", "alpha", "X", "Y", "Z", "brightness"]
    assert set(COLUMNS) == set(table)
    assert summary["exposures"][0]["particles"] == table["x"].size > 0
    truth = read_csv(sim / "IMG_0001.truth.csv")
    nn = mean_nn_mm(sim)
    s = score(table, truth, nn_mm=nn)
    assert s.recall >= 0.85 and s.precision >= 0.85 and s.depth_abs_rms_over_nn < 0.2
    # The camera's own .RAW + .TXT pair gives the same particles as the .lfp.
    out_raw = tmp_path / "raw.csv"
    code, _, _ = run_json(capsys, ["process", str(sim / "IMG_0001.RAW"), "--calibration", str(sim / "calibration"),
                                   "--out", str(out_raw), "--cache", str(tmp_path / "cache")])
    assert code == 0
    assert np.allclose(read_csv(out_raw)["Z"], table["Z"])
    # One line-ending convention (LF), and the same bytes the API serves for this table.
    data = out.read_bytes()
    assert b"\r" not in data and data.count(b"\n") == table["x"].size + 1
    assert data.decode() == table_csv(read_csv(out))


def test_a_batch_csv_has_lf_line_endings(sim, tmp_path, capsys):
    out = tmp_path / "batch.csv"
    code, _, _ = run_json(capsys, ["process", str(sim), "--calibration", str(sim / "calibration"), "--out", str(out),
                                   "--cache", str(tmp_path / "cache"), "--quiet"])
    assert code == 0
    data = out.read_bytes()
    # frame and t (s since the first shot, from the metadata clock) first; index numbers the particles.
    assert b"\r" not in data and data.startswith(b"frame,t,index,")


def test_batch_folder_to_one_table_with_frames_and_stack(sim, tmp_path, capsys):
    out = tmp_path / "run.csv"
    code, summary, _ = run_json(capsys, ["process", str(sim), "--calibration", str(sim / "calibration"), "--out", str(out),
                                         "--no-cache", "--save-stack", "--slices", "30", "--quiet"])
    assert code == 0
    names = [e["exposure"] for e in summary["exposures"]]
    assert [n.rsplit("/", 1)[1] for n in names] == ["IMG_0001.lfp", "IMG_0002.lfp"]  # .RAW twins skipped
    table = read_csv(out)
    assert set(np.unique(table["frame"])) == {0, 1}
    # One frame of the batch, scored against its own truth.
    code, report, _ = run_json(capsys, ["score", str(out), "--frame", "1", "--truth", str(sim / "IMG_0002.truth.csv")])
    assert code == 0 and report["n_found"] == int(np.sum(table["frame"] == 1)) and report["recall"] >= 0.98
    with h5py.File(tmp_path / "run.stack.h5") as f:
        assert f["entry/frames/1/stack"].shape[0] == 30
        assert f["entry/process"].attrs["n_slices"] == 30


def test_batch_to_folder_and_hdf5(sim, tmp_path, capsys):
    out = tmp_path / "results"
    code, summary, _ = run_json(capsys, ["process", str(sim / "IMG_0001.lfp"), str(sim / "IMG_0002.lfp"),
                                         "--calibration", str(sim / "calibration"), "--out", str(out),
                                         "--format", "h5", "--no-cache", "--no-depth-prior", "--no-late-pass"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["IMG_0001.h5", "IMG_0002.h5"]
    with h5py.File(out / "IMG_0002.h5") as f:
        assert f["entry/data"].attrs["NX_class"] == "NXdata" and f["entry/data/Z"].size > 0
        assert not f["entry/process"].attrs["depth_prior"] and f["entry/process"].attrs["deblend"]
        assert not f["entry/process"].attrs["late_pass"]


def test_validate_plane_reads_the_tilt(sim, tmp_path, capsys):
    out = tmp_path / "p.csv"
    assert main(["process", str(sim / "IMG_0001.lfp"), "--calibration", str(sim / "calibration"), "--out", str(out),
                 "--no-cache"]) == 0
    capsys.readouterr()
    code, report, _ = run_json(capsys, ["validate-plane", str(out)])
    assert code == 0
    assert 5 < report["tilt_deg"] < 25  # the simulated layer is tilted 13 degrees
    assert report["rms_over_nn"] < 0.2 and math.isclose(report["rms_over_nn"],
                                                        report["rms_mm"] / report["nn_mean_mm"], rel_tol=1e-9)


def test_bad_inputs_give_clear_errors(sim, tmp_path, capsys):
    code, _, err = run_json(capsys, ["process", str(sim / "IMG_0001.lfp"), "--calibration", str(tmp_path / "nowhere"),
                                     "--out", str(tmp_path / "x.csv")])
    assert code == 2 and "white images" in err
    code, _, err = run_json(capsys, ["process", str(sim / "IMG_0001.lfp"), "--calibration", str(sim / "calibration"),
                                     "--out", str(tmp_path / "x.txt")])
    assert code == 2 and ".csv or .h5" in err
    code, _, err = run_json(capsys, ["process", str(tmp_path), "--calibration", str(sim / "calibration"),
                                     "--out", str(tmp_path / "x.csv")])
    assert code == 2 and "no .lfp" in err
    code, _, err = run_json(capsys, ["process", str(sim / "IMG_0001.lfp"), "--calibration", str(sim / "calibration"),
                                     "--out", str(tmp_path / "x.csv"), "--slices", "2"])
    assert code == 2 and "n_slices" in err
    broken = tmp_path / "IMG_0009.lfp"
    broken.write_bytes(b"not a picture")
    code, summary, err = run_json(capsys, ["process", str(broken), str(sim / "IMG_0001.lfp"), "--calibration",
                                           str(sim / "calibration"), "--out", str(tmp_path / "y.csv"), "--no-cache"])
    assert code == 1 and "IMG_0009" in err
    assert "error" in summary["exposures"][0] and summary["exposures"][1]["particles"] > 0
    code, _, err = run_json(capsys, ["validate-plane", str(tmp_path / "missing.csv")])
    assert code == 2


def test_score_against_the_simulated_truth(sim, tmp_path, capsys):
    out = tmp_path / "p.csv"
    assert main(["process", str(sim / "IMG_0001.lfp"), "--calibration", str(sim / "calibration"), "--out", str(out),
                 "--no-cache"]) == 0
    capsys.readouterr()
    truth = sim / "IMG_0001.truth.csv"
    code, report, _ = run_json(capsys, ["score", str(out), "--truth", str(truth)])
    assert code == 0
    expected = score(read_csv(out), read_csv(truth))
    assert report["n_matched"] == expected.n_matched and report["recall"] == expected.recall
    assert math.isclose(report["depth_fit_rms_over_nn"], expected.depth_fit_rms_over_nn, rel_tol=1e-12)
    assert report["recall"] >= 0.98 and report["depth_fit_rms_over_nn"] < 0.035  # the layer's targets
    # The exposure lies beside the truth: the floor comes along (the layer crosses the focus).
    assert report["depth_floor"]["single_lens"] >= 1 and report["depth_floor"]["rms_over_nn"] > 0
    # Without it, no floor; and a file that is no truth is refused by name.
    alone = tmp_path / "IMG_0001.truth.csv"
    alone.write_bytes(truth.read_bytes())
    code, report, _ = run_json(capsys, ["score", str(out), "--truth", str(alone)])
    assert code == 0 and "depth_floor" not in report
    code, _, err = run_json(capsys, ["score", str(out), "--truth", str(out)])
    assert code == 2 and "truth.csv" in err
