"""A first colorization fill in a fresh process against SciPy's spsolve of the same system.

``bench --only prepare`` times the fill after one untimed fill of the same frame, as a prepare
worker has after its first frame. This times the first one: the solver's plan for the frame's
size and its first use of memory are in it. Run from the repository root, one thread:
``OMP_NUM_THREADS=1 python scripts/time_first_fill.py PREPARED_SPLIT`` (a split folder prepared
with ``dataset.fill=none``, as for ``bench --prepared``); run it once per fresh process.
"""

import sys
import time

import numpy as np
from threadpoolctl import threadpool_limits

from fusion_depth.bench.stages import prepared_frames
from fusion_depth.data.filling import colorization_reference, fill_depth


def main(split: str) -> None:
    threadpool_limits(1)
    image, depth = prepared_frames(split, 1)[0]
    row, col = (int(v) for v in np.argwhere(depth > 0)[0])
    patch = np.s_[max(row - 16, 0) : row + 16, max(col - 16, 0) : col + 16]
    fill_depth(depth[patch], image[patch], "colorization")  # the imports, untimed
    colorization_reference(depth[patch], image[patch])
    start = time.perf_counter()
    ours = fill_depth(depth, image, "colorization")
    ours_s = time.perf_counter() - start
    start = time.perf_counter()
    reference = colorization_reference(depth, image)
    reference_s = time.perf_counter() - start
    print(
        f"first fill {ours_s:.2f} s, spsolve {reference_s:.2f} s: {reference_s / ours_s:.1f}x, "
        f"largest difference {1000 * np.abs(ours - reference).max():.4f} mm"
    )


if __name__ == "__main__":
    main(sys.argv[1])
