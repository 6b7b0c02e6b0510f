"""How fast a run's velocity turns the smoke about the source's vertical axis (issue 18).

  python velocity_turn.py RUN_DIR DATA_DIR FRAMES [--estimate]
      (FRAMES: comma list; needs numpy)

For each frame, over the true smoke (density above 1% of its maximum, cells at least two
from the axis through the box's centre), prints the density-weighted mean angular velocity
about that axis of the run's velocity and of the truth's, in degrees per frame
(counter-clockwise seen from above, as the generator's `swirl_degrees`), and the correlation
of their tangential components. On the turning plume (`reproduce turning`) the truth turns
about 3 degrees per frame; a velocity that carries the turn reads the same. `--estimate`
reads the run's `velocity_estimate/` (`gausmoke-train velocity`) instead of its own velocity.
"""

import sys

import numpy as np

from scene_truth import read_run_and_truth


def main():
    arguments = [a for a in sys.argv[1:] if a != "--estimate"]
    if len(arguments) != 3:
        sys.exit(__doc__)
    run, data = arguments[0], arguments[1]
    folder = "velocity_estimate" if "--estimate" in sys.argv else "frames"
    for t in [int(f) for f in arguments[2].split(",")]:
        ours, density, truth = read_run_and_truth(run, data, t, folder)
        n = density.shape[0]
        centre = (np.arange(n) + 0.5) / n - 0.5
        x, _, z = np.meshgrid(centre, centre, centre, indexing="ij")
        r2 = x**2 + z**2
        inside = (density > 0.01 * density.max()) & (r2 > (2.0 / n) ** 2)
        weight = density[inside]

        def tangential(u):
            return ((u[..., 0] * z - u[..., 2] * x) / np.sqrt(r2))[inside]

        def turn(u):
            return np.degrees(np.sum(weight * tangential(u) / np.sqrt(r2[inside])) / weight.sum())

        corr = np.corrcoef(tangential(ours), tangential(truth))[0, 1]
        print(
            f"frame {t:3}: turns {turn(ours):+.2f} deg/frame (truth {turn(truth):+.2f}); "
            f"tangential correlation {corr:+.2f}"
        )


if __name__ == "__main__":
    main()
