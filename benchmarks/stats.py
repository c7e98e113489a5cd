"""Statistics of RL results over seeds: rliable (Agarwal et al., 2021) to describe, exact tests to judge.

* ``interval_estimates``: IQM and mean of each method's scores with stratified-bootstrap 95% intervals;
* ``paired_probability_of_improvement``: P(X > Y) within pairs of runs measured together, with its
  bootstrap-over-pairs interval;
* ``t_interval``, ``two_sample_t_interval``: Student t 95% intervals of a mean (of paired differences, say) and of a
  difference of independent means (Welch);
* ``sign_flip_test``: the exact one- or two-sided p-value of paired differences over all 2^n sign assignments;
  ``permutation_test``: of two independent groups over all their splits;
* ``paired_claim``, ``two_group_claim``: a claim "the difference is positive" measured by both (estimate,
  t interval, exact p each way) and judged; ``describe``: its test in one line;
* ``outcome`` and ``verdict``: what a difference says of the claim that it is positive, from the exact test and the
  t interval (supported, contradicted, weak or not supported; and a sentence); ``judge``: the same, or "too few
  runs" when a side has fewer than ``MIN_RUNS``; ``SMALL_SAMPLE_NOTE``: why a claim over very few units can at best
  be "weak";
* ``pairs_needed``: the seed pairs a paired t test needs to detect a true mean difference.

Every claim is judged by an exact test (sign-flip or permutation) and a t interval: over the few runs an RL
comparison has (6 or fewer seeds, or seed pairs) a percentile bootstrap's interval is too narrow (over 3 it is the
range of the values). rliable's bootstrap intervals stay as descriptions. The exact tests enumerate here rather
than call ``scipy.stats.permutation_test``: returns kept to cents tie often (600.9 + 601.1 and 601.0 + 601.0 are one
sum in decimal, not in binary), and scipy's tie tolerance (1e-14 relative) counts such splits as unequal (600.9,
600.7, 601.1, 600.9, 601.1 against 601.0, 601.0, 600.8: exact one-sided p 4/7, scipy's 1/2; tests/test_stats.py).
The t intervals equal scipy's ``ttest_1samp`` and ``ttest_ind(equal_var=False)`` intervals and also cover one run
and no spread.

rliable's scores are arrays of shape (runs, tasks); one task is a column of one. The tests and intervals take one
value per run (a run is the unit: several values of one run are not independent).
"""

from __future__ import annotations

import itertools
import math

import numpy as np


def interval_estimates(scores: dict[str, np.ndarray], reps: int = 2000, seed: int = 0) -> dict[str, dict]:
    """Per method: ``iqm`` and ``mean`` with ``iqm_ci`` and ``mean_ci`` (stratified bootstrap, 95%), the same for
    the same `seed`; numpy's global random stream is left as it was."""
    from rliable import library as rly
    from rliable import metrics

    def aggregate(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    scores = {k: np.asarray(v, float) for k, v in scores.items()}
    caller_state = np.random.get_state()  # rliable draws its bootstrap samples from numpy's global stream:
    np.random.seed(seed)  # seeded here, and given back to the caller as it was
    try:
        points, intervals = rly.get_interval_estimates(scores, aggregate, reps=reps)
    finally:
        np.random.set_state(caller_state)
    return {
        name: {
            "iqm": float(points[name][0]), "mean": float(points[name][1]),
            "iqm_ci": (float(intervals[name][0, 0]), float(intervals[name][1, 0])),
            "mean_ci": (float(intervals[name][0, 1]), float(intervals[name][1, 1])),
        }  # fmt: skip
        for name in scores
    }


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


ALPHA = 0.05  # the level of every claim: its exact one-sided p-value below this and its t 95% interval clear of 0
MAX_EXACT = 10**7  # sign assignments or splits an exact test enumerates at most
ALTERNATIVES = ("greater", "less", "two-sided")


def _t(means, variances, sizes, weights, confidence: float) -> tuple[float, tuple[float, float]]:
    """sum_g weights[g] * means[g] with its Student t interval: standard error from each group's sample variance,
    degrees of freedom Welch-Satterthwaite's (for one group, n - 1). No spread: the interval is the point; a
    group of one value: (nan, nan)."""
    estimate = float(sum(w * m for w, m in zip(weights, means)))
    if min(sizes) < 2:
        return estimate, (float("nan"), float("nan"))
    parts = [w**2 * v / n for w, v, n in zip(weights, variances, sizes)]
    var = sum(parts)
    if var <= 0:
        return estimate, (estimate, estimate)
    from scipy import stats as sps

    df = var**2 / sum(part**2 / (n - 1) for part, n in zip(parts, sizes))
    half = float(sps.t.ppf(0.5 + confidence / 2, df)) * math.sqrt(var)
    return estimate, (estimate - half, estimate + half)


def one_per_run(x, what: str) -> np.ndarray:
    """x as one value per run: shape (runs,), or rliable's (runs, 1). Several values a run (rliable's tasks) are
    refused: counted as units, they would make the tests and intervals claim more runs than there are. So is a
    value that is not finite (a failed measurement: NaN compares false both ways, and an exact test would count it
    as neither higher nor lower)."""
    x = np.asarray(x, float)
    if x.ndim == 2 and x.shape[1] == 1:
        x = x[:, 0]
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"{what} needs one value per run for at least one run, of shape (runs,), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{what} needs finite values, got {x.tolist()}")
    return x


def t_interval(x, confidence: float = 0.95) -> tuple[float, tuple[float, float]]:
    """The mean of x (one value per run) with its Student t interval: (mean, (low, high)), mean +- t_{n-1} * sd /
    sqrt(n) (sd with n - 1). Values all equal: the interval is the mean; one run: (nan, nan).

    For [5.4, -18.0, 247.9, 218.8, 166.0, -10.1]: mean 101.67, sd 122.74, t_5 = 2.5706: (101.67, (-27.1, 230.5))."""
    x = one_per_run(x, "t_interval")
    variance = float(np.var(x, ddof=1)) if x.size > 1 else float("nan")
    return _t([x.mean()], [variance], [x.size], [1.0], confidence)


def two_sample_t_interval(x, y, confidence: float = 0.95) -> tuple[float, tuple[float, float]]:
    """mean(x) - mean(y) of independent runs with Welch's t interval (each side's own variance, Welch-Satterthwaite's
    degrees of freedom): a side's spread is not assumed to be the other's. A side of one run: (nan, nan)."""
    x, y = one_per_run(x, "a first group"), one_per_run(y, "a second group")
    var = [float(np.var(v, ddof=1)) if v.size > 1 else float("nan") for v in (x, y)]
    return _t([x.mean(), y.mean()], var, [x.size, y.size], [1.0, -1.0], confidence)


def _p(null: np.ndarray, observed: float, alternative: str) -> float:
    """The share of the null distribution (every assignment, the observed one among them) at least as extreme as
    `observed`; a tie within rounding counts as extreme."""
    if alternative not in ALTERNATIVES:
        raise ValueError(f"alternative must be one of {ALTERNATIVES}, got {alternative!r}")
    tol = 1e-9 * max(1.0, float(np.max(np.abs(null))))
    if alternative == "greater":
        extreme = null >= observed - tol
    elif alternative == "less":
        extreme = null <= observed + tol
    else:
        extreme = np.abs(null) >= abs(observed) - tol
    return float(np.mean(extreme))


def sign_flip_test(diffs, alternative: str = "greater") -> float:
    """The exact p-value of paired differences against "their distribution is symmetric about 0": the mean of
    every one of the 2^n assignments of signs to |diffs| (the observed one included), and the share of them at least
    as large as the observed mean ("greater"), as small ("less"), or as far from 0 ("two-sided"). 3 of 3
    positive: 1/8 one-sided, 2/8 two-sided; the smallest one-sided p over n pairs is 1/2^n (1/32 < 0.05 needs 5
    pairs)."""
    d = one_per_run(diffs, "the sign-flip test")
    if 2**d.size > MAX_EXACT:
        raise ValueError(f"the exact sign-flip test enumerates 2^n assignments: n = {d.size} is not in "
                         f"1..{int(math.log2(MAX_EXACT))}")  # fmt: skip
    assignment, sums = np.arange(2**d.size), np.zeros(2**d.size)
    for i, size in enumerate(np.abs(d)):  # bit i of an assignment's number: the sign of the i-th difference
        sums += np.where((assignment >> i) & 1, -size, size)
    return _p(sums / d.size, float(d.mean()), alternative)


def permutation_test(x, y, alternative: str = "greater") -> float:
    """The exact p-value of independent runs x and y against "they come from one distribution": mean(x') - mean(y')
    for every one of the C(n + m, n) ways to split the n + m runs into groups of n and m (the observed split
    included), and the share of them at least as large as the observed difference ("greater"), as small ("less"),
    or as far from 0 ("two-sided"). The smallest one-sided p is 1/C(n + m, n): 1/20 = 0.05 for 3 and 3 runs, which
    is not below 0.05."""
    x, y = one_per_run(x, "the permutation test"), one_per_run(y, "the permutation test")
    n, m = x.size, y.size
    if math.comb(n + m, n) > MAX_EXACT:
        raise ValueError(f"the exact permutation test enumerates every split: {n} and {m} runs make "
                         f"{math.comb(n + m, n)} splits, more than its limit of {MAX_EXACT}")  # fmt: skip
    pooled, total = np.concatenate([x, y]), float(x.sum() + y.sum())
    firsts = np.fromiter((sum(c) for c in itertools.combinations(pooled, n)), float, math.comb(n + m, n))
    return _p(firsts / n - (total - firsts) / m, float(x.mean() - y.mean()), alternative)


def outcome(ci: tuple[float, float], estimate: float, p: float, p_opposite: float) -> str:
    """The claim "the difference is positive", judged by its exact test (`p`: the one-sided p-value that it is
    greater than 0, `p_opposite`: that it is less), its `estimate` and its t 95% interval `ci`:

    * "supported": p < ALPHA and the interval lies above 0;
    * "contradicted" (the opposite holds): p_opposite < ALPHA and the interval lies below 0;
    * "weak": the estimate is positive, but the test does not reach ALPHA or the interval includes 0;
    * "not supported": otherwise (the estimate is 0 or negative, the opposite not shown either)."""
    low, high = ci
    if p < ALPHA and low > 0:
        return "supported"
    if p_opposite < ALPHA and high < 0:
        return "contradicted"
    return "weak" if estimate > 0 else "not supported"


def verdict(ci: tuple[float, float], estimate: float, p: float, p_opposite: float) -> str:
    """``outcome`` as a sentence that says why: "weak (positive, but the exact test's p = 0.109 is not below
    0.05)"."""
    word = outcome(ci, estimate, p, p_opposite)
    if word == "supported":
        return word
    if word == "contradicted":
        return "contradicted (the opposite holds)"
    if word == "weak":
        if p >= ALPHA:
            return f"weak (positive, but the exact test's p = {p:.3f} is not below {ALPHA})"
        return f"weak (positive and p = {p:.3f}, but the t interval includes 0)"
    if estimate < 0:
        return f"not supported (the estimate is negative; the opposite's p = {p_opposite:.3f})"
    return "not supported (the estimate is not positive)"


MIN_RUNS = 2  # fewer runs than this on a side of a claim: no spread to measure, no t interval, and no verdict
SMALL_SAMPLE_NOTE = (
    "An exact test over few units has a floor: over n seed pairs the sign-flip test's smallest one-sided p is "
    "1/2^n (1/8 for 3 pairs, 1/16 for 4), and over two groups of 3 runs the permutation test's is 1/C(6, 3) = 0.05, "
    "so with fewer than 5 pairs, or two groups whose 1/C(n+m, n) is not below 0.05 (3 and 3 runs, 2 and 4), a claim "
    "is at best \"weak\" however clearly every run agrees."
)


def judge(ci: tuple[float, float], n: int, estimate: float, p: float, p_opposite: float) -> tuple[str, str]:
    """(``outcome``, ``verdict``) when the smaller side of the comparison has `n` >= MIN_RUNS runs, else
    ("too few runs", "too few runs to judge (n = 1)")."""
    if n < MIN_RUNS:
        return "too few runs", f"too few runs to judge (n = {n})"
    return outcome(ci, estimate, p, p_opposite), verdict(ci, estimate, p, p_opposite)


def paired_claim(diffs, confidence: float = 0.95) -> dict:
    """The claim "the mean of paired differences is positive": ``estimate`` (their mean) with its t interval
    ``ci`` (``t_interval``), the exact sign-flip test's one-sided ``p`` (greater) and ``p_opposite`` (less),
    ``n`` the units, ``min_p`` the smallest p the test can give (1/2^n), the ``outcome`` and the ``verdict``
    (``judge``). One difference per unit (a seed pair, a run); up to 23 units (the test is exact)."""
    d = one_per_run(diffs, "a paired claim")
    estimate, ci = t_interval(d, confidence)
    n = d.size
    greater, less = sign_flip_test(d, "greater"), sign_flip_test(d, "less")
    word, said = judge(ci, n, estimate, greater, less)
    return {
        "estimate": estimate, "ci": ci, "p": greater, "p_opposite": less, "n": n, "sizes": f"{n}",
        "test": "sign-flip", "interval": "t", "confidence": confidence, "min_p": 0.5**n, "outcome": word,
        "verdict": said,
    }  # fmt: skip


def two_group_claim(x, y, confidence: float = 0.95) -> dict:
    """The claim "mean(x) - mean(y) is positive" for independent runs: ``estimate`` with Welch's t interval ``ci``
    (``two_sample_t_interval``), the exact permutation test's one-sided ``p`` (greater) and ``p_opposite`` (less),
    ``n`` the smaller side, ``min_p`` = 1/C(n_x + n_y, n_x), the ``outcome`` and the ``verdict`` (``judge``). Up to
    10^7 splits (12 runs a side; the test is exact)."""
    x, y = one_per_run(x, "a first group"), one_per_run(y, "a second group")
    estimate, ci = two_sample_t_interval(x, y, confidence)
    greater, less = permutation_test(x, y, "greater"), permutation_test(x, y, "less")
    n = min(x.size, y.size)
    word, said = judge(ci, n, estimate, greater, less)
    return {
        "estimate": estimate, "ci": ci, "p": greater, "p_opposite": less, "n": n, "sizes": f"{x.size}+{y.size}",
        "test": "permutation", "interval": "Welch t", "confidence": confidence,
        "min_p": 1 / math.comb(x.size + y.size, x.size), "outcome": word, "verdict": said,
    }  # fmt: skip


def describe(claim: dict, digits: int = 1) -> str:
    """The test of a claim (``paired_claim``, ``two_group_claim``) in one line: "sign-flip p=0.109, t 95% [-27.1,
    +230.5], n=6" (p one-sided, of the claim)."""
    low, high = claim["ci"]
    level = f"{100 * claim['confidence']:g}%"
    interval = f"{claim['interval']} {level} [{low:+.{digits}f}, {high:+.{digits}f}]"
    interval = "no interval" if math.isnan(low) else interval
    return f"{claim['test']} p={claim['p']:.3f}, {interval}, n={claim['sizes']}"


def pairs_needed(diffs_sd: float, effect: float, alpha: float = ALPHA, power: float = 0.8,
                 alternative: str = "two-sided") -> int:  # fmt: skip
    """The fewest seed pairs n for which a paired t test at level `alpha` detects a true mean difference `effect`
    with probability `power`, the paired differences' SD being `diffs_sd`: under the effect the statistic is
    noncentral t with n - 1 degrees of freedom and noncentrality effect / diffs_sd * sqrt(n); "two-sided" (the
    default: a t 95% interval clear of 0 on either side; ``verdict`` asks it to lie above 0 and, besides, the
    sign-flip p below 0.05, which needs 5 pairs or more) or "greater". For SD 0.48 (the LSTM-minus-GRU win
    rates after 150 races) and an effect of 0.5: 10 pairs; of 0.3: 23 (one-sided: 8 and 18)."""
    from scipy import stats as sps

    if diffs_sd <= 0 or effect == 0 or alternative not in ("two-sided", "greater"):
        raise ValueError(f"pairs_needed needs diffs_sd > 0, effect != 0 and alternative 'two-sided' or 'greater', "
                         f"got {diffs_sd}, {effect} and {alternative!r}")  # fmt: skip
    for n in range(2, 100_001):
        df, shift = n - 1, abs(effect) / diffs_sd * math.sqrt(n)
        if alternative == "two-sided":
            crit = sps.t.ppf(1 - alpha / 2, df)
            reach = sps.nct.sf(crit, df, shift) + sps.nct.cdf(-crit, df, shift)
        else:
            crit = sps.t.ppf(1 - alpha, df)
            reach = sps.nct.sf(crit, df, shift)
        if reach >= power:
            return n
    raise ValueError(f"more than 100000 pairs for an effect of {effect} at SD {diffs_sd}")
