"""Uncertainty of a paired comparison: is model B really better than model A on this test set?

Two models scored on the same test images give one metric difference per image. The mean of
those differences is what a table reports; whether it is *real* depends on how much it would move
had other test images been drawn and, when several training seeds exist, had the models been
trained again. :func:`paired_bootstrap` answers both with a percentile bootstrap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BootstrapResult", "paired_bootstrap"]

# Resamples × images held in memory at once (float64): ~32 MB, whatever the test-set size.
_CHUNK_CELLS = 4_000_000


@dataclass(frozen=True)
class BootstrapResult:
    """Mean paired difference and its percentile-bootstrap confidence interval."""

    mean: float
    low: float
    high: float
    resamples: int
    level: float
    num_seeds: int
    num_images: int

    @property
    def excludes_zero(self) -> bool:
        """True when the whole interval lies on one side of 0: the difference is significant."""
        return self.low > 0 or self.high < 0


def _check(differences: np.ndarray, resamples: int, level: float) -> np.ndarray:
    d = np.asarray(differences, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(
            f"differences: expected a 2-D array (seeds, images), got shape {d.shape}; "
            "use differences.reshape(1, -1) for a single seed"
        )
    seeds, images = d.shape
    if seeds < 1 or images < 2:
        raise ValueError(f"differences: expected at least 1 seed and 2 images, got shape {d.shape}")
    if not np.isfinite(d).all():
        bad = np.argwhere(~np.isfinite(d))[0]
        raise ValueError(
            f"differences: expected finite values, got {d[tuple(bad)]} at (seed, image) "
            f"{tuple(int(i) for i in bad)}"
        )
    if not (isinstance(resamples, int | np.integer) and resamples >= 1):
        raise ValueError(f"resamples={resamples!r}: expected a positive integer")
    if not 0 < level < 1:
        raise ValueError(f"level={level!r}: expected a confidence level in (0, 1), e.g. 0.95")
    return d


def paired_bootstrap(
    differences: np.ndarray, resamples: int = 10000, level: float = 0.95, seed: int = 0
) -> BootstrapResult:
    """Mean of per-image differences with a two-level percentile-bootstrap interval.

    Args:
        differences: ``(S, N)`` array, ``differences[s, i]`` = metric of model B minus metric of
            model A on test image ``i``, both trained with the ``s``-th shared seed (``S = 1``
            when there is one seed, or when the runs are averaged over seeds first).
        resamples: bootstrap resamples.
        level: confidence level of the interval (0.95 → 2.5th and 97.5th percentiles).
        seed: seed of the resampling, so that a report is reproducible.

    Returns:
        The mean over all seeds and images, and the interval.

    What the interval covers: the variation of the mean difference from drawing *test images*
    (images are resampled with replacement) and, when ``S ≥ 2``, from *training seeds* as well
    (each resample also draws the seeds with replacement; the same image draw is used for every
    seed, since all seeds are scored on the same images). With ``S = 1`` it says nothing about
    how a retrained model would do: a single seed's difference can be significant by luck of
    initialisation. Few seeds (2–3) make the seed level of the interval coarse, not wrong.
    """
    d = _check(differences, resamples, level)
    seeds, images = d.shape
    rng = np.random.default_rng(seed)
    stats = np.empty(resamples)
    chunk = max(1, _CHUNK_CELLS // images)
    for start in range(0, resamples, chunk):
        b = min(chunk, resamples - start)
        draws = rng.integers(0, images, size=(b, images))  # images drawn with replacement
        if seeds == 1:
            stats[start : start + b] = d[0][draws].mean(axis=1)
        else:
            seed_counts = rng.multinomial(seeds, np.full(seeds, 1.0 / seeds), size=b)
            per_image = seed_counts @ d / seeds  # (b, N): mean over each resample's seeds
            stats[start : start + b] = np.take_along_axis(per_image, draws, axis=1).mean(axis=1)
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(stats, [alpha, 1.0 - alpha])
    return BootstrapResult(
        mean=float(d.mean()),
        low=float(low),
        high=float(high),
        resamples=int(resamples),
        level=float(level),
        num_seeds=seeds,
        num_images=images,
    )
