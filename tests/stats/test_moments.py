"""The streaming per-pixel reductions against the same statistics of the whole stack computed at once."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.stats.moments import RunningMoments, RunningPearson


def _stack(seed: int, n: int = 9, shape=(7, 5)):
    """Frames of uint16 counts rising with x as a sensor's do, each pixel with its own gain and noise."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(1.0, 30.0, n))
    gain = rng.uniform(50.0, 150.0, shape)
    y = np.rint(800.0 + gain * x[:, None, None] + rng.normal(0.0, 40.0, (n,) + shape)).astype(np.uint16)
    return x, y


@pytest.mark.parametrize("left_out", [False, True])
def test_running_pearson_is_the_correlation_of_each_pixels_valid_samples(left_out):
    """Per pixel, r of the samples it was valid in equals np.corrcoef of those samples (to 1e-12, float64 sums
    of at most 9 values below 5e3); a pixel with fewer than 3 valid samples, or whose y never varies, is NaN;
    float32 output is the float64 result rounded."""
    x, y = _stack(3)
    rng = np.random.default_rng(4)
    valid = rng.uniform(size=y.shape) > 0.2 if left_out else np.ones(y.shape, bool)
    if left_out:
        valid[2:, 0, 0] = False                # two samples only: NaN
        valid[:2, 0, 0] = True
    y[:, 0, 1] = 1000                          # no spread: NaN
    acc = RunningPearson()
    for k in range(len(x)):
        acc.add(x[k], y[k], valid[k] if left_out else None)
    r = acc.r()
    for i in range(y.shape[1]):
        for j in range(y.shape[2]):
            ok = valid[:, i, j]
            if ok.sum() < 3 or np.ptp(y[ok, i, j]) == 0:
                assert np.isnan(r[i, j]), (i, j)
                continue
            want = np.corrcoef(x[ok], y[ok, i, j].astype(float))[0, 1]
            assert abs(r[i, j] - want) < 1e-12, (i, j, r[i, j], want)
    np.testing.assert_array_equal(acc.r(np.float32), r.astype(np.float32))


def test_running_moments_are_the_stack_mean_and_unbiased_variance():
    """Mean and ddof=1 variance of each pixel over the frames, to 1e-9 relative (shifted float64 sums)."""
    _, y = _stack(5)
    acc = RunningMoments()
    for frame in y:
        acc.add(frame)
    np.testing.assert_allclose(acc.mean(), y.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(acc.variance(), y.astype(float).var(axis=0, ddof=1), rtol=1e-9)


def test_histogram_counts_are_numpys_for_equal_step_edges():
    """Every value's bin as np.histogram puts it: on each edge, just below and above it, at the last edge
    (the closed last bin), outside the range (left out), means of integer frames (k / 15) that fall on 0.5-DN
    edges; and edges of unequal steps (numpy's own search)."""
    from pipeline.stats.moments import histogram_counts

    rng = np.random.default_rng(4)
    edges = np.arange(760.3, 900.3 + 1e-9, 0.5)
    on = np.concatenate([edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf)])
    frames = 800 + rng.integers(-40, 120, (200_000, 15)).mean(axis=1)
    values = np.concatenate([on, frames, [700.0, 1000.0, edges[-1]]])
    assert np.array_equal(histogram_counts(values, edges), np.histogram(values, bins=edges)[0])
    uneven = np.array([0.0, 1.0, 3.0, 3.5, 10.0])
    x = rng.uniform(-1, 11, 10_000)
    assert np.array_equal(histogram_counts(x, uneven), np.histogram(x, bins=uneven)[0])
