"""Time the simulator on full-size F01 frames (3280 x 3280) and print the figures.

Run: ``.venv/bin/python bench/bench_simulate.py [--repeat N]``. Prints seconds per full-size white
image, per exposure of each scenario, and per complete ``write_scenario`` (one exposure, five
white images, all files), plus the process's peak resident memory.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import best_time, peak_rss_mb  # noqa: E402

from analysis.camera.model import CameraModel  # noqa: E402
from analysis.simulation.scenarios import SCENARIO_NAMES, make_scenario  # noqa: E402
from analysis.simulation.camera import simulated_camera_metadata  # noqa: E402
from analysis.simulation.render import accumulate_particles, render_exposure, render_white_image  # noqa: E402
from analysis.simulation.scenario_files import write_scenario  # noqa: E402



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    model = CameraModel.from_metadata(simulated_camera_metadata())
    render_white_image(model, seed=0)  # compile / warm the numba kernel
    print(f"full-size white image: {best_time(lambda: render_white_image(model, seed=1), args.repeat):.2f} s")
    import numpy as np
    for name in SCENARIO_NAMES:
        s = make_scenario(name, 1)
        rays = best_time(lambda: accumulate_particles(model, s.particles, rng=np.random.default_rng(0)), args.repeat)
        full = best_time(lambda: render_exposure(model, s.particles, seed=1,
                                                           background_dn=s.background_dn), args.repeat)
        print(f"{name:13s} {len(s.particles):4d} particles: ray tracing {rays:.2f} s, "
              f"full exposure (glow, blur, noise) {full:.2f} s")
    with tempfile.TemporaryDirectory() as tmp:
        t = best_time(lambda: write_scenario(Path(tmp) / "run", "tilted-layer", 1), 1)
        print(f"write_scenario full size (1 exposure + 5 white images, all files): {t:.2f} s")
    peak_mib = peak_rss_mb()
    print(f"peak resident memory: {peak_mib:.0f} MiB")


if __name__ == "__main__":
    main()
