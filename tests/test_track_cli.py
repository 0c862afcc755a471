"""`plenodust track` and `plenodust link` on a small simulated run, against its truth; and the
trackpy user's way in (Result.to_dataframe into trackpy.link)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pandas as pd
import pytest

from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.track_scoring import read_truth_run, score_tracks
from service.cli.main import main

SHOTS = 4
RANGE = ["--alpha-min", "0.999", "--alpha-max", "1.026"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run")
    write_scenario(folder, "ball", 12, count=SHOTS, size=640, centre_z_mm=57.4, progress=lambda line: None)
    return folder


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One calibration and look-up table cache for the run's camera, as a lab's machine keeps."""
    return tmp_path_factory.mktemp("cache")


def test_track_links_a_run_in_shot_time_order_and_recovers_the_truth(run, cache, tmp_path, capsys) -> None:
    out = tmp_path / "tracks.csv"
    summary = tmp_path / "structure.csv"
    code = main(["track", str(run), "--calibration", str(run / "calibration"), "--out", str(out), *RANGE,
                 "--summary", str(summary), "--cache", str(cache), "--quiet"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    linked = pd.read_csv(out)
    assert list(linked.columns[:13]) == ["frame", "t", "particle", "index", "x", "y", "alpha", "X", "Y", "Z",
                                         "vX", "vY", "vZ"]
    assert report["frames"] == SHOTS and report["trajectories"] == linked["particle"].nunique()
    assert sorted(linked["t"].unique()) == pytest.approx([0.0, 1.0, 2.0, 3.0])
    score = score_tracks(linked, read_truth_run(run))
    assert score["links_judged"] > 50 and score["links_right"] >= 0.97
    assert score["fragments_per_particle"] < 1.15
    # Velocities within a fraction of the true speeds (lateral; depth is the noisy axis), where the
    # links are right (the few wrong ones are judged above: each puts a step of about an NN in).
    err, speed = score["velocity_rms_error_right_links_mm_s"], score["true_speed_rms_mm_s"]
    assert err[0] < 0.5 * speed[0] and err[1] < 0.5 * speed[1]
    structure = pd.read_csv(summary)
    assert structure["frame"].tolist() == list(range(SHOTS))
    assert structure["count"].tolist() == linked.groupby("frame").size().tolist()


def test_link_takes_a_processed_table_and_writes_nexus(run, cache, tmp_path, capsys) -> None:
    table = tmp_path / "run.csv"
    assert main(["process", str(run), "--calibration", str(run / "calibration"), "--out", str(table), *RANGE,
                 "--cache", str(cache), "--quiet"]) == 0
    capsys.readouterr()
    processed = pd.read_csv(table)
    assert "t" in processed and "particle" not in processed  # the batch's clock; no trajectories yet
    out = tmp_path / "tracks.h5"
    assert main(["link", str(table), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    with h5py.File(out, "r") as f:
        data = f["entry/data"]
        assert data.attrs["signal"] == "Z"
        linked = pd.DataFrame({name: data[name][()] for name in ("frame", "particle", "X", "Y", "Z", "vX")})
        assert "linking" in json.loads(f["entry/process/parameters"][()])
    assert report["trajectories"] == linked["particle"].nunique()
    assert score_tracks(linked.assign(vY=np.nan, vZ=np.nan), read_truth_run(run))["links_right"] >= 0.97
    # A table without t needs the interval: said so, exit 2.
    no_t = tmp_path / "no_t.csv"
    processed.drop(columns="t").to_csv(no_t, index=False)
    assert main(["link", str(no_t), "--out", str(tmp_path / "x.csv")]) == 2
    assert "--interval" in capsys.readouterr().err


# trackpy 0.7 calls sort_values(inplace=True), which pandas 3.1 deprecates.
@pytest.mark.filterwarnings("ignore:The inplace keyword")
def test_a_trackpy_user_links_results_with_trackpy_itself(run, cache) -> None:
    import trackpy

    from analysis.cache import Cache
    from analysis.calibration.cache import load_calibration
    from analysis.formats.exposure import read_exposure
    from analysis.pipeline.params import PipelineParams
    from analysis.pipeline.process import process

    frames, tables = [], Cache(directory=cache)
    for k, path in enumerate(sorted(run.glob("IMG_*.lfp"))):
        exposure = read_exposure(path)
        calibration = load_calibration(run / "calibration", exposure.metadata, serial=exposure.serial,
                                       cache_dir=cache)
        result = process(exposure, calibration, PipelineParams(alpha_min=0.999, alpha_max=1.026), cache=tables)
        frames.append(result.to_dataframe(frame=k, t=float(k)))
    table = pd.concat(frames, ignore_index=True)
    assert list(table.columns[:4]) == ["frame", "t", "index", "x"]
    trackpy.quiet()
    linked = trackpy.link(table, 0.25, pos_columns=["X", "Y", "Z"], memory=1)
    assert score_tracks(linked.assign(vX=np.nan, vY=np.nan, vZ=np.nan), read_truth_run(run))["links_right"] >= 0.9
