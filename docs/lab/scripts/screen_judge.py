"""usage: screen_judge.py NAME VARIANT   rules 1-3 of "Screens on the combination" (docs/lab/screens.md, fixed
2026-12-06 before any of their runs) on a screen's two seeds: sweep_NAME.csv (seed 11) and sweep_NAME12.csv (seed 12)
in /work/screens3/benchmarks/results/screening. Prints each rule; exits 0 when all three pass, 1 otherwise."""
import csv
import os
import sys

SCREENING = os.environ.get("SCREENING", "/work/screens3/benchmarks/results/screening")
# per variant: rule 2's means (mean action, sampled) and rule 3's average, from the combination's policies
THRESHOLDS = {"lstm": (498.13, 679.55, 663.84), "gru": (449.42, 627.66, 613.54)}
STEER = 0.3  # rule 1: the mean action's |steer| per seed

name, variant = sys.argv[1], sys.argv[2]
rows = {}
for seed, path in ((11, f"sweep_{name}.csv"), (12, f"sweep_{name}12.csv")):
    path = os.path.join(SCREENING, path)
    if not os.path.exists(path):
        sys.exit(f"{name}: no {path} (the screen stopped at seed 11, or seed 12 is not reported yet): not passed")
    mine = [r for r in csv.DictReader(open(path)) if r["variant"] == variant and int(r["seed"]) == seed]
    if len({r["tag"] for r in mine}) > 1:
        sys.exit(f"{name}: {path} holds several flag sets; judge one at a time")
    rows |= {(seed, r["policy"]): r for r in mine}
missing = [(s, p) for s in (11, 12) for p in ("mean-action", "stochastic") if (s, p) not in rows]
if missing:
    sys.exit(f"{name}: no row for {missing}")
mean_action = [float(rows[s, "mean-action"]["return"]) for s in (11, 12)]
sampled = [float(rows[s, "stochastic"]["return"]) for s in (11, 12)]
steer = [float(rows[s, "mean-action"]["abs_steer"]) for s in (11, 12)]
low_mean, low_sampled, low_average = THRESHOLDS[variant]
rule1 = all(x <= STEER for x in steer)
rule2 = sum(mean_action) / 2 >= low_mean and sum(sampled) / 2 >= low_sampled
rule3 = (sum(mean_action) + sum(sampled)) / 4 >= low_average
print(f"{name} ({variant}): rule 1 |steer| {steer[0]:.2f}, {steer[1]:.2f}: {'pass' if rule1 else 'FAIL'}; rule 2 mean "
      f"action {sum(mean_action) / 2:.2f} (>= {low_mean}), sampled {sum(sampled) / 2:.2f} (>= {low_sampled}): "
      f"{'pass' if rule2 else 'FAIL'}; rule 3 average {(sum(mean_action) + sum(sampled)) / 4:.2f} (>= {low_average}): "
      f"{'pass' if rule3 else 'FAIL'}")
sys.exit(0 if rule1 and rule2 and rule3 else 1)
