"""Full-size refocus benchmark: look-up table, 40-slice stack, sub-aperture image, products.

Prints wall times (best of repeats after warm-up: the machine is shared, so the minimum is the
uncontended figure), peak memory of a fresh process that
loads the cached table and refocuses, and the ratio against a naive dense per-slice splat.

    .venv/bin/python bench/bench_refocus.py [--particles 360] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import peak_rss_mb  # noqa: E402
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))

import numpy as np  # noqa: E402


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")



def _timed(fn, repeats: int) -> tuple[float, object]:
    times = []
    result = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times), result


def prepare(folder: Path, n_particles: int, seed: int) -> None:
    """Simulated full-size exposure (with plasma glow), white image, table cached with its norms."""
    from analysis.camera.model import CameraModel
    from analysis.lightfield.table import build_table_from_model, save_table
    from analysis.lightfield.refocus import default_alphas, normalisation, subaperture_image
    from analysis.simulation.scenarios import Particles, make_scenario
    from analysis.simulation.camera import simulated_camera_metadata
    from analysis.simulation.render import render_exposure, render_white_image

    model = CameraModel.from_metadata(simulated_camera_metadata())
    parts = []
    k = 0
    while sum(len(p.x_mm) for p in parts) < n_particles:
        name = ("ball", "tilted-layer", "shadowing")[k % 3]
        p = make_scenario(name, seed + k).particles
        shift = (k % 3 - 1) * 4.0
        parts.append(Particles(p.x_mm + shift, p.y_mm + (k // 3) * 3.0 - 3.0, p.z_mm, p.brightness_dn))
        k += 1
    particles = Particles(*(np.concatenate([getattr(p, f) for p in parts])[:n_particles]
                            for f in ("x_mm", "y_mm", "z_mm", "brightness_dn")))
    t0 = time.perf_counter()
    raw = render_exposure(model, particles, seed=seed, background_dn=40.0, samples_per_side=100)
    print(f"simulated exposure: {len(particles.x_mm)} particles, glow 40 DN ({time.perf_counter() - t0:.1f} s)")
    white = render_white_image(model, noise=False)
    dev = (white.astype(np.float32) - model.black_level) / (model.white_level - model.black_level)
    np.save(folder / "raw.npy", raw)

    t_build, table = _timed(lambda: build_table_from_model(model, dev), 1)
    print(f"table build:         {t_build * 1e3:8.1f} ms  ({table.n_samples} samples, {table.n_lenses} lenses, "
          f"grid {table.grid.width} x {table.grid.height})")
    alphas = default_alphas()
    t0 = time.perf_counter()
    normalisation(table, alphas)
    t_norm = time.perf_counter() - t0
    t0 = time.perf_counter()
    subaperture_image(raw, table)
    t_sub_norm = time.perf_counter() - t0
    print(f"normalisation (once per table + alphas, incl. compile if cold): {t_norm * 1e3:.0f} ms; "
          f"sub-aperture first call: {t_sub_norm * 1e3:.0f} ms")
    t_save, _ = _timed(lambda: save_table(table, folder / "table.npz"), 1)
    size_mb = (folder / "table.npz").stat().st_size / 2 ** 20
    print(f"table save:          {t_save * 1e3:8.1f} ms  ({size_mb:.0f} MB on disk, normalisations included)")


def worker(folder: Path, repeats: int, naive: bool) -> None:
    """A fresh process: load the cached table, refocus, time it, report memory."""
    import numba

    from analysis.lightfield import refocus as rf
    from analysis.lightfield.samples import select_samples
    from analysis.lightfield.table import load_table

    base = _rss_mb()
    t_load, table = _timed(lambda: load_table(folder / "table.npz"), 1)
    raw = np.load(folder / "raw.npy")
    alphas = rf.default_alphas()
    # Warm-up: numba loads its cached kernels.
    t0 = time.perf_counter()
    samples = select_samples(raw, table)
    stack = rf.refocus_stack(raw, table, alphas, samples=samples)
    sub = rf.subaperture_image(raw, table, samples=samples)
    prod = rf.products(stack, sub)
    t_first = time.perf_counter() - t0
    print(f"threads: {numba.get_num_threads()}; process RSS after imports {base:.0f} MB")
    print(f"table load:          {t_load * 1e3:8.1f} ms")
    print(f"first call (kernels from numba cache): {t_first * 1e3:.0f} ms")

    t_sel, samples = _timed(lambda: select_samples(raw, table), repeats)
    t_stack, _ = _timed(lambda: rf.refocus_stack(raw, table, alphas, samples=samples, out=stack), repeats)
    t_sub, sub = _timed(lambda: rf.subaperture_image(raw, table, samples=samples), repeats)
    t_prod, _ = _timed(lambda: rf.products(stack, sub, out=prod), repeats)
    total = t_sel + t_stack + t_sub + t_prod
    print(f"samples kept:        {samples.ids.size} of {table.n_samples} "
          f"({100 * samples.ids.size / table.n_samples:.1f} %), background {samples.background:.1f} DN, "
          f"noise {samples.sigma:.2f} DN")
    print(f"select samples:      {t_sel * 1e3:8.1f} ms")
    print(f"refocus 40 slices:   {t_stack * 1e3:8.1f} ms")
    print(f"sub-aperture:        {t_sub * 1e3:8.1f} ms")
    print(f"products:            {t_prod * 1e3:8.1f} ms")
    print(f"total (table cached):{total * 1e3:8.1f} ms  (budget for this share: 500 ms)")

    def chain():
        s = select_samples(raw, table)
        rf.refocus_stack(raw, table, alphas, samples=s, out=stack)
        rf.products(stack, rf.subaperture_image(raw, table, samples=s), out=prod)

    t_chain, _ = _timed(chain, repeats)
    print(f"the four in a row:   {t_chain * 1e3:8.1f} ms  (as the pipeline calls them; "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, threading layer "
          f"{numba.threading_layer()})")
    print(f"peak RSS:            {peak_rss_mb():8.0f} MB  (whole process; budget 600 MB for the pipeline)")
    for method in ("triangles", "bilinear"):
        t_m, _ = _timed(lambda: rf.refocus_stack(raw, table, alphas, samples=samples, method=method, out=stack),
                        repeats)
        print(f"refocus, method {method:9s}: {t_m * 1e3:6.1f} ms")

    t_dense, _ = _timed(lambda: rf.refocus_stack(raw, table, alphas, noise_sigmas=None, out=stack), 1)
    print(f"dense refocus (every sample, same kernels): {t_dense * 1e3:.0f} ms "
          f"= {t_dense / t_stack:.1f} x the sparse one")
    if naive:
        t_naive = naive_dense(raw, table, alphas)
        print(f"naive per-slice dense splat, 40 slices: {t_naive * 1e3:.0f} ms "
              f"({t_naive / len(alphas) * 1e3:.0f} ms per slice); "
              f"ours is {t_naive / (t_sel + t_stack):.0f} x faster")


def naive_dense(raw: np.ndarray, table, alphas: np.ndarray) -> float:
    """A naive numba splat: one slice at a time, every sample, serial, bilinear onto the grid,
    normalised the same way."""
    from numba import njit

    @njit(cache=False)
    def one_slice(flat, pix, lens, lens_px, u, v, w, inv_step, coeff, black, width, height, num, den):
        for k in range(pix.size):
            fc = lens_px[lens[k], 0] + u[k] * inv_step * coeff
            fr = lens_px[lens[k], 1] + v[k] * inv_step * coeff
            c0 = int(np.floor(fc))
            r0 = int(np.floor(fr))
            if c0 < 0 or r0 < 0 or c0 + 1 >= width or r0 + 1 >= height:
                continue
            a = fc - c0
            b = fr - r0
            val = flat[pix[k]] - black
            for dc, dr, wt in ((0, 0, (1 - a) * (1 - b)), (1, 0, a * (1 - b)), (0, 1, (1 - a) * b), (1, 1, a * b)):
                num[r0 + dr, c0 + dc] += wt * val
                den[r0 + dr, c0 + dc] += wt * w[k]

    grid = table.grid
    col, row = grid.to_pixels(table.lens_xy_m[:, 0], table.lens_xy_m[:, 1])
    lens_px = np.stack([col, row], axis=1).astype(np.float32)
    flat = raw.reshape(-1)
    out = np.empty((len(alphas), grid.height, grid.width), np.float32)
    args = (flat, table.pixel_index, table.lens, lens_px, table.u_m, table.v_m, table.weight, 1.0 / grid.step_m)
    shape = (grid.height, grid.width)
    one_slice(*args, 0.0, float(table.black_level), grid.width, grid.height,
              np.zeros(shape, np.float32), np.zeros(shape, np.float32))  # compile
    t0 = time.perf_counter()
    for a, alpha in enumerate(alphas):
        num = np.zeros(shape, np.float32)
        den = np.zeros(shape, np.float32)
        one_slice(*args, 1.0 / alpha - 1.0, float(table.black_level), grid.width, grid.height, num, den)
        np.divide(num, den, out=out[a], where=den > 0)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=360)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--no-naive", action="store_true", help="skip the naive baseline")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.repeats, not args.no_naive)
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        prepare(folder, args.particles, args.seed)
        cmd = [sys.executable, __file__, "--worker", str(folder), "--repeats", str(args.repeats)]
        if args.no_naive:
            cmd.append("--no-naive")
        subprocess.run(cmd, check=True)


if __name__ == "__main__":
    main()
