"""benchmarks/stats.py: the exact tests, the t intervals, the verdict over few runs and the pairs a paired t test
needs, against values derived by hand (or by a brute force written apart from the implementation)."""

import itertools
import math

import numpy as np
import pytest

import stats

# benchmarks/results/ghost_vs_control.csv: return after the ghost stage - after its control, per (variant, seed)
GHOST = [5.4, -18.0, 247.9, 218.8, 166.0, -10.1]
T_975 = {2: 4.302653, 4: 2.776445, 5: 2.570582}  # Student t quantiles (tables) by degrees of freedom


def test_the_t_interval_of_the_ghost_differences_is_mean_plus_minus_t5_standard_errors():
    mean = sum(GHOST) / 6  # 610.0 / 6
    sd = math.sqrt(sum((d - mean) ** 2 for d in GHOST) / 5)  # 122.74
    half = T_975[5] * sd / math.sqrt(6)  # 2.5706 * 50.11 = 128.80
    estimate, (low, high) = stats.t_interval(GHOST)
    assert estimate == pytest.approx(101.67, abs=0.005) and sd == pytest.approx(122.74, abs=0.005)
    assert (low, high) == pytest.approx((mean - half, mean + half), abs=1e-4)
    assert (low, high) == pytest.approx((-27.14, 230.47), abs=0.01)
    assert stats.t_interval([50.0] * 4) == (50.0, (50.0, 50.0))  # no spread: the interval is the point
    assert all(math.isnan(v) for v in stats.t_interval([5.0])[1])  # one run: no interval


def test_the_welch_t_interval_matches_its_formula_and_a_run_is_the_unit():
    # x 1, 2, 3 (variance 1), y 10, 10, 10 (variance 0): -8 +- t_2 * sqrt(1/3); the degrees of freedom are x's alone
    diff, (low, high) = stats.two_sample_t_interval([1.0, 2.0, 3.0], [10.0, 10.0, 10.0])
    assert diff == -8.0 and (low, high) == pytest.approx((-8 - T_975[2] / math.sqrt(3), -8 + T_975[2] / math.sqrt(3)))
    # several values a run (3 runs, 2 tasks each) would count as 6 units: p = 1/64 and an interval too narrow for 3
    three_runs = np.array([[1.0, 101.0], [2.0, 102.0], [3.0, 103.0]])
    for measure in (stats.t_interval, stats.sign_flip_test, stats.paired_claim):
        with pytest.raises(ValueError, match=r"one value per run.*\(3, 2\)"):
            measure(three_runs)
    with pytest.raises(ValueError, match="one value per run"):
        stats.two_group_claim(three_runs, [1.0, 2.0])
    # their means per run are the units: 51, 52, 53, p = 1/8 and 52 +- t_2 * 1 / sqrt(3)
    claim = stats.paired_claim(three_runs.mean(axis=1))
    half = T_975[2] / math.sqrt(3)
    assert claim["p"] == 1 / 8 and claim["ci"] == pytest.approx((52 - half, 52 + half))
    assert stats.t_interval(three_runs[:, :1]) == stats.t_interval([1.0, 2.0, 3.0])  # rliable's (runs, 1): a run each


def test_the_sign_flip_test_counts_every_sign_assignment():
    # 3 of 3 positive: only the observed assignment reaches the observed mean, 1 of 8
    assert stats.sign_flip_test([1.0, 2.0, 3.0]) == 1 / 8
    assert stats.sign_flip_test([1.0, 2.0, 3.0], "two-sided") == 2 / 8  # all plus or all minus
    assert stats.sign_flip_test([1.0, 2.0, 3.0], "less") == 1.0
    # The ghost: |d| sums to 666.2, the observed sum is 610.0; an assignment with negative set N sums to
    # 666.2 - 2 sum(N) >= 610.0 iff sum(N) <= 28.1: N = {}, {5.4}, {10.1}, {18.0}, {5.4, 10.1}, {5.4, 18.0},
    # {10.1, 18.0} (the observed one): 7 of 64 one-sided, 14 of 64 two-sided (the distribution is symmetric)
    assert stats.sign_flip_test(GHOST) == 7 / 64 == 0.109375
    assert stats.sign_flip_test(GHOST, "two-sided") == 14 / 64 == 0.21875
    # the same counts by brute force over sign tuples, on the rounded-to-cents sums (no tolerance needed)
    cents = [round(abs(d) * 10) for d in GHOST]
    sums = [sum(s * c for s, c in zip(signs, cents)) for signs in itertools.product((1, -1), repeat=6)]
    observed = sum(round(d * 10) for d in GHOST)
    assert sum(t >= observed for t in sums) == 7 and sum(abs(t) >= observed for t in sums) == 14
    assert stats.sign_flip_test([0.0, 0.0, 1.0]) == 4 / 8  # a zero difference flips to itself: a tie each time
    with pytest.raises(ValueError, match="alternative"):
        stats.sign_flip_test([1.0], "bigger")


def test_the_permutation_test_counts_every_split():
    # 1, 2, 3 against 4, 5, 6: of the C(6, 3) = 20 splits only the observed one has x's mean 3 below y's
    assert stats.permutation_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0], "less") == 1 / 20
    assert stats.permutation_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0], "two-sided") == 2 / 20
    assert stats.permutation_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]) == 1.0
    # 0, 10 against 5: splits {0, 10 | 5} -> 0, {0, 5 | 10} -> -7.5, {5, 10 | 0} -> +7.5
    assert stats.permutation_test([0.0, 10.0], [5.0]) == 2 / 3
    assert stats.permutation_test([0.0, 10.0], [5.0], "two-sided") == 1.0
    x, y = [3.0, 9.0, 4.0, 8.0], [1.0, 7.0, 2.0]  # against a brute force over index subsets
    pooled, observed = x + y, np.mean(x) - np.mean(y)
    diffs = [np.mean([pooled[i] for i in s]) - np.mean([pooled[i] for i in range(7) if i not in s])
             for s in itertools.combinations(range(7), 4)]  # fmt: skip
    assert len(diffs) == 35
    assert stats.permutation_test(x, y) == pytest.approx(sum(d >= observed - 1e-12 for d in diffs) / 35)


def scipy_split_p(x, y, alternative):
    """scipy.stats.permutation_test's p of mean(x) - mean(y) over every split of two independent groups."""
    import scipy.stats

    def difference(a, b, axis):
        return np.mean(a, axis=axis) - np.mean(b, axis=axis)

    return scipy.stats.permutation_test((x, y), difference, permutation_type="independent", alternative=alternative,
                                        n_resamples=np.inf, vectorized=True).pvalue  # fmt: skip


def test_the_exact_tests_count_ties_of_returns_in_cents_as_rational_arithmetic_does():
    """Returns kept to cents tie often (600.9 + 601.1 and 601.0 + 601.0 are one sum in decimal, not in binary):
    every split and sign assignment is compared as exact fractions of the decimal values, the reference here.
    scipy.stats.permutation_test's tie tolerance (1e-14 relative) misses these ties: 1/2 and 0.607 for the first
    pair below, where the exact p-values are 4/7 and 5/8."""
    from fractions import Fraction

    def exact_split_p(x, y, alternative):
        pool, n, m = [Fraction(v) for v in x + y], len(x), len(y)
        observed = sum(map(Fraction, x)) / n - sum(map(Fraction, y)) / m
        null = [sum(pool[i] for i in c) / n - (sum(pool) - sum(pool[i] for i in c)) / m
                for c in itertools.combinations(range(n + m), n)]  # fmt: skip
        extreme = [d >= observed if alternative == "greater" else d <= observed for d in null]
        return Fraction(sum(extreme), len(null))

    def exact_flip_p(d, alternative):
        d = [Fraction(v) for v in d]
        null = [sum(s * abs(v) for s, v in zip(signs, d)) for signs in itertools.product((1, -1), repeat=len(d))]
        extreme = [t >= sum(d) if alternative == "greater" else t <= sum(d) for t in null]
        return Fraction(sum(extreme), len(null))

    pairs = [(["600.9", "600.7", "601.1", "600.9", "601.1"], ["601.0", "601.0", "600.8"]),
             (["601.1", "600.8", "600.7", "600.9"], ["601.1", "601.0", "600.7", "601.0", "600.8", "600.8"]),
             (["0.3", "0.1", "0.2"], ["0.2", "0.3", "0.1", "0.6"])]  # fmt: skip
    assert exact_split_p(*pairs[0], "greater") == Fraction(4, 7) and exact_split_p(*pairs[0], "less") == Fraction(5, 8)
    # scipy's exhaustive p misses these ties (scipy 1.x: 1/2 and 17/28 = 0.607, both below the exact p): the reason
    # stats.py enumerates its own (should a scipy count them, this fails and the reason is gone)
    first = [[float(v) for v in side] for side in pairs[0]]
    for alternative in ("greater", "less"):
        assert scipy_split_p(*first, alternative) < float(exact_split_p(*pairs[0], alternative)) - 1e-3
    for x, y in pairs:
        for alternative in ("greater", "less"):
            p = stats.permutation_test([float(v) for v in x], [float(v) for v in y], alternative)
            assert p == pytest.approx(float(exact_split_p(x, y, alternative)), abs=1e-12)
    for d in (["0.1", "0.2", "-0.3", "0.4"], ["600.9", "-601.1", "601.0", "-601.0", "0.2"]):
        for alternative in ("greater", "less"):
            p = stats.sign_flip_test([float(v) for v in d], alternative)
            assert p == pytest.approx(float(exact_flip_p(d, alternative)), abs=1e-12)


def test_the_t_intervals_are_scipys_where_scipy_gives_one():
    """t_interval and two_sample_t_interval against scipy.stats.ttest_1samp and ttest_ind(equal_var=False)'s
    confidence intervals, an implementation written apart; the cases scipy leaves out (one run, no spread) are
    above."""
    from scipy import stats as sps

    rng = np.random.default_rng(3)
    for n, m in [(2, 2), (3, 5), (5, 5), (6, 3)]:
        x, y = rng.normal(600, 150, n), rng.normal(550, 60, m)
        one, two = sps.ttest_1samp(x, 0.0).confidence_interval(0.95), sps.ttest_ind(x, y, equal_var=False)
        assert stats.t_interval(x)[1] == pytest.approx((one.low, one.high), rel=1e-9)
        welch = two.confidence_interval(0.95)
        assert stats.two_sample_t_interval(x, y)[1] == pytest.approx((welch.low, welch.high), rel=1e-9)


def test_a_claim_is_supported_only_by_the_exact_test_and_the_t_interval_together():
    # 1..6: p = 1/64 and the t interval 3.5 +- 2.5706 * 1.8708 / sqrt(6) = [1.54, 5.46] above 0
    assert stats.paired_claim([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])["verdict"] == "supported"
    against = stats.paired_claim([-1.0, -2.0, -3.0, -4.0, -5.0, -6.0])
    assert against["outcome"] == "contradicted" and against["verdict"].startswith("contradicted")
    # every difference positive (p = 1/64), but one far out: mean 17.5, sd 40.4, the interval [-24.9, 59.9]
    spread = stats.paired_claim([1.0, 1.0, 1.0, 1.0, 1.0, 100.0])
    assert spread["p"] == 1 / 64 and spread["verdict"].startswith("weak (positive and p = 0.016, but the t interval")
    # 3 of 3 agree, the interval above 0, yet 1/8 is the test's floor: weak
    three = stats.paired_claim([1.0, 1.1, 1.2])
    assert three["ci"][0] > 0 and three["min_p"] == 1 / 8 and three["verdict"].startswith("weak")
    assert stats.paired_claim([-1.0, 1.0])["verdict"] == "not supported (the estimate is not positive)"
    assert stats.paired_claim([-1.0, -2.0, 0.5])["verdict"].startswith("not supported (the estimate is negative")
    assert stats.paired_claim([5.0])["verdict"] == "too few runs to judge (n = 1)"
    assert stats.paired_claim([5.0])["outcome"] == "too few runs"
    # two groups of 3: the permutation test's floor is 1/20 = 0.05, not below 0.05, however far apart they are
    apart = stats.two_group_claim([600.0, 700.0, 800.0], [100.0, 200.0, 300.0])
    assert apart["p"] == 1 / 20 and apart["ci"][0] > 0 and apart["outcome"] == "weak"
    assert apart["verdict"].startswith("weak")
    assert stats.two_group_claim([600.0, 700.0, 800.0, 900.0], [100.0, 200.0, 300.0])["verdict"] == "supported"


def test_the_ghost_claim_is_weak_where_a_percentile_bootstrap_said_supported():
    diffs = np.array(GHOST)
    boot = stats.interval_estimates({"d": diffs[:, None]}, reps=2000)["d"]["mean_ci"]
    assert boot[0] > 0  # the bootstrap's interval is too narrow over 6: by it alone the claim would hold
    claim = stats.paired_claim(diffs)
    assert claim["estimate"] == pytest.approx(101.67, abs=0.005) and claim["p"] == 7 / 64
    assert claim["verdict"] == "weak (positive, but the exact test's p = 0.109 is not below 0.05)"
    assert stats.describe(claim) == "sign-flip p=0.109, t 95% [-27.1, +230.5], n=6"


def test_the_pairs_a_paired_t_test_needs():
    # SD of the LSTM-minus-GRU win rates after 150 races in benchmarks/results/head_to_head.csv: 0.63 - 0.36,
    # 0.18 - 0.82, 0.52 - 0.43 = 0.27, -0.64, 0.09; mean -0.0933, sum of squares 0.4645 over 2: SD 0.482
    sd = float(np.std([0.27, -0.64, 0.09], ddof=1))
    assert sd == pytest.approx(0.4819, abs=1e-4)
    # normal approximation with Guenther's correction, n = (z_.975 + z_.8)^2 (sd / effect)^2 + z_.975^2 / 2:
    # effect 0.5: 7.849 * 0.929 + 1.92 = 9.2 -> 10; effect 0.3: 7.849 * 2.580 + 1.92 = 22.2 -> 23
    assert stats.pairs_needed(sd, 0.5) == 10 and stats.pairs_needed(sd, 0.3) == 23
    assert stats.pairs_needed(sd, -0.5) == 10  # a difference either way
    # one-sided, n = (z_.95 + z_.8)^2 (sd / effect)^2 + z_.95^2 / 2: effect 0.5: 6.183 * 0.929 + 1.353 = 7.1 -> 8;
    # effect 0.3: 6.183 * 2.580 + 1.353 = 17.3 -> 18
    assert stats.pairs_needed(sd, 0.5, alternative="greater") == 8  # one-sided asks fewer
    assert stats.pairs_needed(sd, 0.3, alternative="greater") == 18
    # the power at 10 pairs, by simulation of the paired t test (two-sided, 5%): about 0.83; at 9 about 0.78
    rng = np.random.default_rng(0)
    for n, lowest, highest in ((10, 0.81, 0.85), (9, 0.76, 0.80)):
        d = rng.normal(0.5, sd, size=(40_000, n))
        t = d.mean(axis=1) / (d.std(axis=1, ddof=1) / math.sqrt(n))
        crit = {10: 2.262157, 9: 2.306004}[n]  # t_.975 with 9 and 8 degrees of freedom
        assert lowest < np.mean(np.abs(t) > crit) < highest


def test_the_bootstrap_intervals_repeat_for_a_seed_and_leave_the_callers_random_stream_alone():
    scores = {"a": np.array([[100.0], [300.0], [250.0], [900.0], [640.0]])}
    np.random.seed(123)
    expected_next = np.random.random_sample()
    np.random.seed(123)
    first = stats.interval_estimates(scores, reps=200, seed=7)
    assert np.random.random_sample() == expected_next  # the caller's stream goes on where it was
    assert stats.interval_estimates(scores, reps=200, seed=7) == first
    assert stats.interval_estimates(scores, reps=200, seed=8)["a"]["mean_ci"] != first["a"]["mean_ci"]  # it is the seed
    assert first["a"]["mean"] == 438.0 and first["a"]["iqm"] == (300.0 + 250.0 + 640.0) / 3
    low, high = first["a"]["mean_ci"]
    assert 100.0 <= low < 438.0 < high <= 900.0


def test_the_mean_and_iqm_intervals_are_the_bootstrap_quantiles_of_their_own_statistic():
    """One score of 1000 among five 0s: a resample of 5 runs holds k ~ Binomial(5, 0.2) of the 1000s. Its mean is
    200 k, its IQM (the mean of the middle 3) 0 for k <= 1, 333.3 for k = 2, 666.7 for k = 3. P(k >= 3) = 0.058 and
    P(k >= 4) = 0.007 put the 97.5% quantile at k = 3, P(k = 0) = 0.33 the 2.5% quantile at k = 0: the mean's interval
    is [0, 600], the IQM's [0, 666.7] (points 200 and 0)."""
    est = stats.interval_estimates({"a": np.array([[0.0], [0.0], [1000.0], [0.0], [0.0]])}, reps=2000)["a"]
    assert (est["mean"], est["iqm"]) == (pytest.approx(200.0), pytest.approx(0.0))
    assert est["mean_ci"] == (pytest.approx(0.0), pytest.approx(600.0))
    assert est["iqm_ci"] == (pytest.approx(0.0), pytest.approx(2000 / 3))


def test_a_value_that_is_not_finite_is_refused_not_counted():
    """NaN compares false both ways: an exact test would count a failed measurement as neither higher nor lower."""
    with pytest.raises(ValueError, match=r"^a first group needs finite values, got \[1\.0, nan\]$"):
        stats.two_group_claim([1.0, float("nan")], [2.0, 3.0])
    with pytest.raises(ValueError, match="the sign-flip test needs finite values"):
        stats.sign_flip_test([1.0, float("inf")])
