"""Speed, memory and accuracy of calibration on a full-size simulated F01 white image (3280 x 3280).

Renders a white image (and a dark decoy) with the simulator, writes them as the camera's
``MOD_nnnn.RAW``/``.TXT``, then measures in a fresh process (so its peak RSS is calibration's
alone): the lattice fit, the whole ``calibrate`` (decode, fit, devignetting map), a cache miss
(fit + atomic write) and a cache hit through ``load_calibration``, peak memory (tracemalloc,
which sees NumPy's buffers, and the peak RSS), and the mean micro-image centre error against
the rendered lattice, with the seed perturbed as a real metadata seed can be.

Run: .venv/bin/python bench/bench_calibration.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import best_time, peak_rss_mb  # noqa: E402
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))

from analysis.calibration.calibrate import calibrate
from analysis.calibration.cache import load_calibration, read_calibration, cache_path  # noqa: E402
from analysis.camera.model import CameraModel, Lattice  # noqa: E402
from analysis.calibration.lattice_fit import fit_lattice  # noqa: E402
from analysis.simulation.camera import simulated_camera_metadata, simulated_private_metadata  # noqa: E402
from analysis.simulation.render import render_white_image  # noqa: E402
from analysis.formats.whites import WhiteImage, load_white_images, write_white_pair  # noqa: E402

SIZE = 3280
SERIAL = "A202160042"
# PlenoptiCam's calibration step on an F01 white image, 2 cores (design.md, the issue).
PLENOPTICAM_S = 120.0



def prepare(folder: Path) -> Lattice:
    meta = simulated_camera_metadata(size=SIZE)
    model = CameraModel.from_metadata(meta)
    lat = model.lattice
    truth = lat.with_changes(origin_x=lat.origin_x + 0.37, origin_y=lat.origin_y - 0.21, rotation_rad=0.0031)
    private = simulated_private_metadata(SERIAL)
    white = render_white_image(model.with_lattice(truth), seed=1)
    write_white_pair(WhiteImage.from_image("MOD_0002", white, meta, private), folder)
    dark = render_white_image(model.with_lattice(truth), level=150.0, seed=2)
    write_white_pair(WhiteImage.from_image("MOD_0001", dark, meta, private), folder)
    return truth



def centre_error(fitted: Lattice, truth: Lattice) -> float:
    ij, xy = truth.centres(SIZE, SIZE)
    fx, fy = fitted.centre(ij[:, 0], ij[:, 1])
    return float(np.mean(np.hypot(fx - xy[:, 0], fy - xy[:, 1])))


def measure(folder: Path, truth: Lattice) -> None:
    import numba

    from analysis.calibration.lattice_fit import balance_channels, demodulate, lens_centroids

    rss_imports = peak_rss_mb()
    meta = simulated_camera_metadata(size=SIZE)
    white = next(w for w in load_white_images(folder) if w.name == "MOD_0002")
    raw = white.image()
    seed = truth.with_changes(origin_x=truth.origin_x + 3.0, origin_y=truth.origin_y - 2.0,
                              pitch_px=truth.pitch_px * 1.002, rotation_rad=truth.rotation_rad - 0.001,
                              scale_y=1.0)
    t0 = time.perf_counter()
    fit = fit_lattice(raw, seed)
    first = time.perf_counter() - t0
    t_fit = best_time(lambda: fit_lattice(raw, seed), 3)
    t_cal = best_time(lambda: calibrate(white), 3)
    t_decode = best_time(lambda: white.image(), 3)
    image = balance_channels(raw, black_level=168.0)
    t_balance = best_time(lambda: balance_channels(raw, black_level=168.0), 3)
    t_demod = best_time(lambda: demodulate(image, seed), 3)
    t_centroids = best_time(lambda: lens_centroids(image, fit.lattice), 3)

    tracemalloc.start()
    cal = calibrate(white)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp)
        t0 = time.perf_counter()
        load_calibration(folder, meta, serial=SERIAL, cache_dir=cache)
        t_miss = time.perf_counter() - t0
        t_hit = best_time(lambda: load_calibration(folder, meta, serial=SERIAL, cache_dir=cache), 5)
        path = cache_path(cache, SERIAL, cal.white_sha1)
        t_read = best_time(lambda: read_calibration(path), 5)
        size_mib = path.stat().st_size / 2**20
    rss_mib = peak_rss_mb()

    print(f"numba threads                      {numba.get_num_threads()}")
    print(f"fit_lattice, first call            {first:7.3f} s   (numba cache load or compile)")
    print(f"fit_lattice, best of 3             {t_fit:7.3f} s   ({PLENOPTICAM_S / t_fit:,.0f}x faster "
          f"than PlenoptiCam's ~{PLENOPTICAM_S:.0f} s; target < 3 s)")
    print(f"  of which balance channels        {t_balance:7.3f} s")
    print(f"  of which demodulate (3 freqs)    {t_demod:7.3f} s")
    print(f"  of which centroid check          {t_centroids:7.3f} s   (the rest: robust least squares)")
    print(f"calibrate (decode+fit+devignette)  {t_cal:7.3f} s   (decode alone {t_decode:.3f} s)")
    print(f"load_calibration, cache miss       {t_miss:7.3f} s   (choose white, SHA-1, fit, write)")
    print(f"load_calibration, cache hit        {t_hit:7.3f} s   ({t_miss / t_hit:.0f}x faster than a miss)")
    print(f"read_calibration alone             {t_read:7.3f} s   (cache file {size_mib:.0f} MiB)")
    print(f"peak traced memory in calibrate    {peak / 2**20:7.0f} MiB")
    print(f"peak RSS of this process           {rss_mib:7.0f} MiB   ({rss_imports:.0f} MiB after imports)")
    print(f"lenses measured / blocks fitted    {fit.n_lenses} / {fit.n_blocks}")
    print(f"fit residual rms                   {fit.rms_px:7.4f} px   (centroid rms {fit.centroid_rms_px:.3f} px)")
    print(f"mean centre error vs truth         {centre_error(fit.lattice, truth):7.4f} px   (target < 0.05 px; "
          f"seed off by 3.6 px, 0.2 % pitch, 1 mrad)")
    print(f"mean centre error, metadata seed   {centre_error(cal.lattice, truth):7.4f} px")


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--measure":
        measure(Path(sys.argv[2]), Lattice(**json.loads(sys.argv[3])))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(f"rendering a {SIZE} x {SIZE} white image and a dark decoy ...", flush=True)
        truth = prepare(folder)
        lattice = json.dumps({k: getattr(truth, k) for k in
                              ("origin_x", "origin_y", "pitch_px", "rotation_rad", "scale_x", "scale_y")})
        subprocess.run([sys.executable, __file__, "--measure", str(folder), lattice], check=True)


if __name__ == "__main__":
    main()
