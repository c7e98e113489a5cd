#!/bin/bash
# screen_chain.sh.
# usage: [VARIANTS=gru] screen_chain.sh NAME GRID "BUDGET at seed 11" "BUDGET at seed 12": the screen of GRID (clone
# /work/screens3) at seed 11 (sweep NAME), its report, and at seed 12 (sweep NAME12) only if seed 11's mean action
# keeps |steer| <= 0.3 (the stopping rule), then its report. Each step resumes, or skips when done. Rules 2 and 3
# (both seeds): screen_judge.py NAME VARIANT (the lane scripts start a GRU part when the LSTM's passes).
# A sweep whose report (sweep_NAME.csv) holds both policies' rows of its seed is done and skipped. A new machine has
# no clone: make it (once, under a lock: the two lanes start together) at the commit the screens' rules were fixed
# on, with the reports main has committed since (so that a screen measured on the old machine is not run again).
results=/work/screens3/benchmarks/results/screening
(
  flock 9
  if [ ! -d /work/screens3 ]; then
    rm -rf /work/screens3.tmp
    git clone -q ${MAIN:-/work/main} /work/screens3.tmp && git -C /work/screens3.tmp checkout -q 723951d || exit 1
    cp -n ${MAIN:-/work/main}/benchmarks/results/screening/sweep_*.csv /work/screens3.tmp/benchmarks/results/screening/ || exit 1
    mv /work/screens3.tmp /work/screens3 || exit 1
  fi
) 9> /work/logs/screens3.lock || exit 1
cd /work/screens3
name=$1; grid=$2; b11=$3; b12=$4; variants=${VARIANTS:-lstm}
reported() {  # reported SWEEP SEED: its report holds both policies' rows of SEED for $variants
  python - "$results/sweep_$1.csv" "$2" "$variants" <<'PY'
import csv, os, sys
path, seed, variant = sys.argv[1:]
rows = list(csv.DictReader(open(path))) if os.path.exists(path) else []
policies = {r["policy"] for r in rows if r["seed"] == seed and r["variant"] == variant}
sys.exit(0 if {"mean-action", "stochastic"} <= policies else 1)
PY
}
if ! reported $name 11; then
  python benchmarks/sweep.py --name $name --grid "$grid" --variants $variants --seeds 11 $b11 --num-cpus 1 >> /work/logs/sweep_$name.log 2>&1 || exit 1
  python benchmarks/sweep.py --name $name --report >> /work/logs/sweep_$name.log 2>&1 || exit 1
fi
if python - "$name" <<'PY'
import csv, sys
path = f"/work/screens3/benchmarks/results/screening/sweep_{sys.argv[1]}.csv"
rows = [r for r in csv.DictReader(open(path)) if r["policy"] == "mean-action"]
sys.exit(0 if rows and all(float(r["abs_steer"]) <= 0.3 for r in rows) else 1)
PY
then
  reported ${name}12 12 && exit 0
  python benchmarks/sweep.py --name ${name}12 --grid "$grid" --variants $variants --seeds 12 $b12 --num-cpus 1 >> /work/logs/sweep_${name}12.log 2>&1 || exit 1
  python benchmarks/sweep.py --name ${name}12 --report >> /work/logs/sweep_${name}12.log 2>&1
else
  echo "$(date -u) $name: seed 11 breaks rule 1; the screen ends" >> /work/logs/sweep_$name.log
fi
