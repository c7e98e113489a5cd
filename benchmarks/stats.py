"""Statistics of RL results over seeds, with rliable (Agarwal et al., 2021).

* ``interval_estimates``: IQM and mean of each method's scores with stratified-bootstrap 95% intervals;
* ``paired_probability_of_improvement``: P(X > Y) within pairs of runs measured together, with its
  bootstrap-over-pairs interval;
* ``mean_difference``: mean(X) - mean(Y) of independent runs, with its stratified-bootstrap interval;
* ``verdict``: what an interval of a difference says of the claim that it is positive; ``judge``: the same, or
  "too few runs" when a side has fewer than ``MIN_RUNS``; ``SMALL_SAMPLE_NOTE``: what an interval over 3 runs or
  fewer is.

Scores are arrays of shape (runs, tasks), rliable's layout; one task is a column of one.
"""

from __future__ import annotations

import numpy as np


def interval_estimates(scores: dict[str, np.ndarray], reps: int = 2000, seed: int = 0) -> dict[str, dict]:
    """Per method: ``iqm`` and ``mean`` with ``iqm_ci`` and ``mean_ci`` (stratified bootstrap, 95%)."""
    from rliable import library as rly
    from rliable import metrics

    def aggregate(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    np.random.seed(seed)  # rliable draws its bootstrap samples from numpy's global stream
    scores = {k: np.asarray(v, float) for k, v in scores.items()}
    points, intervals = rly.get_interval_estimates(scores, aggregate, reps=reps)
    return {
        name: {
            "iqm": float(points[name][0]), "mean": float(points[name][1]),
            "iqm_ci": (float(intervals[name][0, 0]), float(intervals[name][1, 0])),
            "mean_ci": (float(intervals[name][0, 1]), float(intervals[name][1, 1])),
        }  # fmt: skip
        for name in scores
    }


def two_sample_estimate(x: np.ndarray, y: np.ndarray, statistic, reps: int = 2000, seed: int = 0):
    """statistic(x, y) of independent runs x (runs_x, tasks) and y (runs_y, tasks), each resampled on its own
    (rliable's stratified independent bootstrap), with its 95% interval: (estimate, (low, high))."""
    from rliable import library as rly

    np.random.seed(seed)  # rliable draws its bootstrap samples from numpy's global stream
    pair = {"x,y": (np.asarray(x, float), np.asarray(y, float))}
    points, intervals = rly.get_interval_estimates(pair, statistic, reps=reps)
    low, high = np.asarray(intervals["x,y"], float).reshape(-1)  # rliable gives the interval as a (2, 1) array
    return float(points["x,y"]), (float(low), float(high))


def paired_probability_of_improvement(x: np.ndarray, y: np.ndarray, reps: int = 2000, seed: int = 0) -> dict:
    """P(X > Y) for paired runs: the share of pairs i with x[i] > y[i] (a tie counts one half), with its 95%
    interval from a bootstrap over pairs (rliable's, on the per-pair outcomes).

    For two agents measured in the same races (a seed pair's head-to-head win rates) this is the question "in how
    many pairs does X beat Y". rliable's probability of improvement treats x and y as independent samples and
    compares every x[i] with every y[j], across pairs whose races have nothing in common, and resamples each
    side apart, which breaks the pairing: for (0.55, 0.45), (0.35, 0.65), (0.60, 0.40) it gives 4/9 although
    X wins two pairs of three."""
    x, y = np.asarray(x, float).reshape(-1), np.asarray(y, float).reshape(-1)
    if x.shape != y.shape or x.size == 0:
        raise ValueError(f"paired runs need two non-empty arrays of one length, got {x.size} and {y.size}")
    outcome = (x > y) + 0.5 * (x == y)
    est = interval_estimates({"pairs": outcome[:, None]}, reps=reps, seed=seed)["pairs"]
    return {"p": est["mean"], "ci": est["mean_ci"]}


def mean_difference(x: np.ndarray, y: np.ndarray, reps: int = 2000, seed: int = 0) -> dict:
    """mean(X) - mean(Y) of independent runs x and y, with its 95% interval. For paired runs, take the differences
    and use ``interval_estimates`` on them instead."""
    diff, ci = two_sample_estimate(x, y, lambda a, b: np.mean(a) - np.mean(b), reps, seed)
    return {"diff": diff, "ci": ci}


def verdict(ci: tuple[float, float]) -> str:
    """The claim "the difference is positive", judged by its 95% interval."""
    low, high = ci
    if low > 0:
        return "supported"
    if high < 0:
        return "contradicted (the opposite holds)"
    return "not supported (the interval includes 0)"


MIN_RUNS = 2  # fewer runs than this on a side of a claim: its bootstrap interval has no width, and no verdict
SMALL_SAMPLE_NOTE = (
    "A mean over 3 runs or fewer: the bootstrap's 95% interval spans their smallest to their largest value (a "
    "resample of one run repeated has probability (1/n)^n > 2.5%), so \"supported\" there means that every run "
    "agrees, not a test at the 5% level."
)


def judge(ci: tuple[float, float], n: int) -> str:
    """``verdict(ci)`` when the smaller side of the comparison has `n` >= MIN_RUNS runs, else "too few runs"."""
    return verdict(ci) if n >= MIN_RUNS else f"too few runs to judge (n = {n})"
