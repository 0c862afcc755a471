"""Hot, stuck and dead pixels found from a camera's calibration frames, and kept out of the pipeline."""

from __future__ import annotations

import json
import logging
import os
import shutil

import numpy as np
import pytest

from analysis.cache import Cache
from analysis.calibration.cache import load_calibration
from analysis.calibration.camera_defects import defects_cache_path
from analysis.calibration.white_choice import defect_search_frames, select_white_image
from analysis.formats.exposure import read_exposure
from analysis.formats.particle_table import read_csv
from analysis.formats.whites import load_white_images
from analysis.pipeline.params import PipelineParams
from analysis.pipeline.process import process
from analysis.pipeline.tables import FIT_TABLE_RIM_PX, REFOCUS_TABLE_RIM_PX, get_table, table_cache_path
from analysis.simulation.camera_effects import SensorDefects
from analysis.simulation.realism import Realism
from analysis.simulation.render import white_coverage
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scoring import score

HOT, DEAD = 1e-3, 2e-4   # ten times a typical sensor's, for statistics on a crop


def defect_truth(serial: str, size: int, hot: float = HOT, dead: float = DEAD):
    return SensorDefects.draw(serial, hot_fraction=hot, dead_fraction=dead).on_crop(size, size)


@pytest.fixture(scope="module", params=["A202160042", "A100000001", "A31415926"])
def defective(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp(f"defects-{request.param}")
    write_scenario(folder, "ball", 1, size=512, serial=request.param,
                   realism=Realism(hot_pixel_fraction=HOT, dead_pixel_fraction=DEAD))
    return folder, request.param


def test_defects_are_found_for_each_camera(defective):
    folder, serial = defective
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cal = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial)
    size = exposure.image.shape[0]
    truth = defect_truth(serial, size)
    flat = truth.rows * size + truth.cols
    found = np.isin(flat, cal.defects.index)
    lit = white_coverage(exposure.model)[truth.rows, truth.cols] > 0.05
    hot = truth.kind == SensorDefects.HOT
    assert found[hot & (truth.level_dn >= 100)].mean() >= 0.97
    assert found[truth.kind == SensorDefects.STUCK].all()
    assert found[(truth.kind == SensorDefects.DEAD) & lit].mean() >= 0.95
    # Warm pixels (20 ... 100 DN) drown in the frames' noise unless the dark frame shows them.
    assert found[hot & (truth.level_dn < 100)].mean() >= 0.15
    false = np.setdiff1d(cal.defects.index, flat)
    rows, cols = np.divmod(false, size)
    inner = np.minimum(np.minimum(rows, size - 1 - rows), np.minimum(cols, size - 1 - cols)) >= 2
    # The crop's outermost rows and columns differ from their neighbours (the simulator blurs a crop with
    # its edge mirrored): a few of them are flagged. Elsewhere, false alarms are rare.
    assert inner.sum() <= 1e-4 * size * size
    kinds = dict(zip(cal.defects.index.tolist(), cal.defects.kind.tolist()))
    assert all(kinds[int(i)] == cal.defects.HOT for i in flat[truth.kind != SensorDefects.DEAD] if int(i) in kinds)


def test_an_ideal_sensor_has_no_defects(tmp_path):
    write_scenario(tmp_path, "ball", 2, size=512)
    exposure = read_exposure(tmp_path / "IMG_0001.lfp")
    cal = load_calibration(tmp_path / "calibration", exposure.metadata, serial=exposure.serial)
    rows, cols = np.divmod(cal.defects.index, 512)
    assert np.sum(np.minimum(np.minimum(rows, 511 - rows), np.minimum(cols, 511 - cols)) >= 2) <= 5


def test_the_look_up_tables_leave_defects_out(defective):
    folder, _ = defective
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cal = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial)
    plain = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial, find_defects=False)
    cache = Cache(directory=folder / "tables")
    for rim in (REFOCUS_TABLE_RIM_PX, FIT_TABLE_RIM_PX):
        table = get_table(cal, cache, rim_px=rim)
        before = get_table(plain, cache, rim_px=rim)
        assert not np.isin(table.pixel_index, cal.defects.index).any()
        assert np.isin(before.pixel_index, cal.defects.index).sum() > 20
        assert table.n_samples + np.isin(before.pixel_index, cal.defects.index).sum() == before.n_samples
        # Kept apart on disk: the table with defects left out is named by the defect map too.
        assert table_cache_path(cache.directory, cal, 1.0, rim) != table_cache_path(cache.directory, plain, 1.0, rim)
        assert table_cache_path(cache.directory, cal, 1.0, rim).is_file()


@pytest.mark.parametrize("serial", ["A202160042", "A777"])
def test_a_hot_pixel_never_becomes_a_particle(tmp_path, serial):
    write_scenario(tmp_path, "tilted-layer", 1, size=800, serial=serial,
                   realism=Realism(hot_pixel_fraction=3e-4, dead_pixel_fraction=6e-5))
    exposure = read_exposure(tmp_path / "IMG_0001.lfp")
    truth = read_csv(tmp_path / "IMG_0001.truth.csv")
    nn = json.loads((tmp_path / "scenario.json").read_text())["exposures"][0]["mean_nn_distance_mm"]
    scores = {}
    for find in (False, True):
        cal = load_calibration(tmp_path / "calibration", exposure.metadata, serial=exposure.serial, find_defects=find)
        # Without the map, a laxer misfit limit than the default lets hot pixels through (so this
        # test can fail); the default's alone drops some of them as misfits.
        params = PipelineParams() if find else PipelineParams(max_fit_residual=0.35)
        result = process(exposure, cal, params, cache=Cache())
        scores[find] = score(result.particles, truth, nn_mm=nn)
    assert scores[False].n_found > scores[False].n_matched
    assert scores[True].n_found == scores[True].n_matched == scores[True].n_true


def test_defect_map_is_cached_by_the_frames_it_came_from(defective, tmp_path, caplog):
    folder, serial = defective
    calibration = tmp_path / "calibration"
    shutil.copytree(folder / "calibration", calibration)
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cache = tmp_path / "cache"
    first = load_calibration(calibration, exposure.metadata, serial=serial, cache_dir=cache)
    path = defects_cache_path(cache, serial, first.defects.key)
    assert path.is_file()
    mtime = path.stat().st_mtime_ns
    second = load_calibration(calibration, exposure.metadata, serial=serial, cache_dir=cache)
    assert path.stat().st_mtime_ns == mtime
    np.testing.assert_array_equal(second.defects.index, first.defects.index)
    np.testing.assert_array_equal(second.defects.kind, first.defects.kind)
    assert second.defects.frames == first.defects.frames
    # A damaged file is searched again and rewritten.
    path.write_bytes(b"not a defect map")
    with caplog.at_level(logging.WARNING):
        third = load_calibration(calibration, exposure.metadata, serial=serial, cache_dir=cache)
    assert "unusable" in caplog.text
    np.testing.assert_array_equal(third.defects.index, first.defects.index)
    # Another frame set (one white image less) is another map, under another key.
    os.remove(calibration / "MOD_0004.RAW")
    os.remove(calibration / "MOD_0004.TXT")
    fewer = load_calibration(calibration, exposure.metadata, serial=serial, cache_dir=cache)
    assert fewer.defects.key != first.defects.key and "MOD_0004" not in fewer.defects.frames
    assert defects_cache_path(cache, serial, fewer.defects.key).is_file()


def test_search_frames_are_the_chosen_white_and_the_nearest_others(defective):
    folder, serial = defective
    exposure = read_exposure(folder / "IMG_0001.lfp")
    whites = load_white_images(folder / "calibration")
    chosen = select_white_image(whites, exposure.metadata, serial=serial)
    frames = defect_search_frames(whites, chosen, exposure.metadata, serial=serial)
    assert frames[0] == (chosen, False)
    assert [(w.name, dark) for w, dark in frames] == [
        ("MOD_0002", False), ("MOD_0001", True), ("MOD_0000", False), ("MOD_0003", False), ("MOD_0004", False)]
    few = defect_search_frames(whites, chosen, exposure.metadata, serial=serial, max_bright=2, max_dark=0)
    assert [w.name for w, _ in few] == ["MOD_0002", "MOD_0000"]
    assert defect_search_frames(whites, chosen, exposure.metadata, serial="A999")[1:] == []


def test_one_white_image_alone_still_shows_the_hot_pixels(defective, tmp_path):
    folder, serial = defective
    calibration = tmp_path / "calibration"
    calibration.mkdir()
    for suffix in (".RAW", ".TXT"):
        shutil.copy(folder / "calibration" / f"MOD_0002{suffix}", calibration)
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cal = load_calibration(calibration, exposure.metadata, serial=serial)
    truth = defect_truth(serial, 512)
    strong = (truth.kind != SensorDefects.DEAD) & (truth.level_dn >= 600)
    assert np.isin((truth.rows * 512 + truth.cols)[strong], cal.defects.index).mean() >= 0.8
    false = np.setdiff1d(cal.defects.index, truth.rows * 512 + truth.cols)
    rows, cols = np.divmod(false, 512)
    assert np.sum(np.minimum(np.minimum(rows, 511 - rows), np.minimum(cols, 511 - cols)) >= 2) <= 30
