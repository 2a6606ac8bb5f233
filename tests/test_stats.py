"""The paired bootstrap: coverage of a known difference, seeds, determinism, input checks."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_depth.metrics.bootstrap import BootstrapResult, paired_bootstrap


def test_interval_covers_a_known_difference_and_excludes_zero() -> None:
    d = np.random.default_rng(0).normal(0.3, 1.0, size=(1, 400))
    r = paired_bootstrap(d)
    assert isinstance(r, BootstrapResult)
    assert r.low < 0.3 < r.high
    assert r.low > 0 and r.excludes_zero
    assert r.mean == pytest.approx(d.mean())
    assert (r.resamples, r.level, r.num_seeds, r.num_images) == (10000, 0.95, 1, 400)
    # The percentile interval of a mean is about ± 1.96 standard errors wide.
    assert r.high - r.low == pytest.approx(2 * 1.96 * d.std() / np.sqrt(400), rel=0.1)


def test_large_shift_excludes_zero_and_no_shift_includes_it() -> None:
    rng = np.random.default_rng(1)
    large = paired_bootstrap(rng.normal(2.0, 1.0, size=(1, 50)))
    assert large.low > 0 and large.excludes_zero
    none = paired_bootstrap(rng.normal(0.0, 1.0, size=(1, 400)))
    assert none.low < 0 < none.high and not none.excludes_zero
    negative = paired_bootstrap(rng.normal(-1.0, 0.5, size=(3, 100)))
    assert negative.high < 0 and negative.excludes_zero


def test_coverage_is_close_to_the_level() -> None:
    """Over 100 simulated test sets, about 95 intervals contain the true difference."""
    rng = np.random.default_rng(2)
    hits = 0
    for k in range(100):
        r = paired_bootstrap(rng.normal(0.3, 1.0, size=(1, 200)), resamples=1000, seed=k)
        hits += r.low < 0.3 < r.high
    assert 85 <= hits <= 100


def test_hierarchical_interval_widens_when_seeds_disagree() -> None:
    rng = np.random.default_rng(3)
    agree = rng.normal(0.3, 1.0, size=(3, 250))
    disagree = agree + np.array([[-1.0], [0.0], [1.0]])  # same mean, seed-dependent shift
    a, b = paired_bootstrap(agree), paired_bootstrap(disagree)
    assert a.mean == pytest.approx(b.mean)
    assert (b.high - b.low) > 3 * (a.high - a.low)
    assert b.low < 0 < b.high and a.excludes_zero
    assert a.num_seeds == 3 and a.num_images == 250


def test_identical_seeds_match_the_single_seed_interval() -> None:
    d = np.random.default_rng(4).normal(0.3, 1.0, size=(1, 300))
    one, three = paired_bootstrap(d), paired_bootstrap(np.repeat(d, 3, axis=0))
    assert three.low == pytest.approx(one.low, abs=0.01)
    assert three.high == pytest.approx(one.high, abs=0.01)


def test_deterministic_given_seed() -> None:
    d = np.random.default_rng(5).normal(0.0, 1.0, size=(2, 100))
    assert paired_bootstrap(d, seed=7) == paired_bootstrap(d, seed=7)
    assert paired_bootstrap(d, seed=7) != paired_bootstrap(d, seed=8)
    narrow = paired_bootstrap(d, resamples=500, level=0.8)
    wide = paired_bootstrap(d, resamples=500, level=0.99)
    assert (narrow.resamples, narrow.level) == (500, 0.8)
    assert wide.low < narrow.low < narrow.high < wide.high


@pytest.mark.parametrize(
    ("differences", "kwargs", "message"),
    [
        (np.zeros(10), {}, "expected a 2-D array"),
        (np.zeros((1, 1)), {}, "at least 1 seed and 2 images"),
        (np.zeros((0, 5)), {}, "at least 1 seed and 2 images"),
        (np.array([[0.0, np.nan, 1.0]]), {}, "expected finite values"),
        (np.zeros((1, 5)), {"level": 1.5}, "level=1.5"),
        (np.zeros((1, 5)), {"resamples": 0}, "resamples=0"),
    ],
)
def test_invalid_input_is_named(differences, kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        paired_bootstrap(differences, **kwargs)
