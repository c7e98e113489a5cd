#!/bin/bash
# usage: switch2.sh   once all 10 runs of the second final protocol are done (docs/lab/final_protocol.md, "The second
# final protocol"), from a clean checkout of main with the runs under $FINAL2/runs/final2_<variant>/trials.
# The switch's mechanical part, as that section fixed it before any second-protocol run was measured:
#  1. the first protocol's learning_final.csv, .md, .png and learning_final_readings.csv move (git mv) to
#     benchmarks/results/history/cpu_float32/;
#  2. benchmarks/final_protocol.py: PROTOCOL_SEEDS becomes (31, 32, 33, 34, 35), REPLACED_PROTOCOL names the first
#     protocol ("cpu_float32", seeds 21..25);
#  3. every run's row and readings on the report tracks (learning.py --protocol-row), then the report
#     (--protocol-report: learning_final.md with the comparison against the first protocol).
# Left by hand: tests that name the first protocol's seeds or OLD_PROTOCOL_HOME's advice, the README's table (the
# first protocol's to docs/lab/learning_history.md), --protocol-ship, the log entry. Review `git diff` before
# committing.
set -euo pipefail
main=${MAIN:-/work/main}; final2=${FINAL2:-/work/final2}
cd $main
for variant in lstm gru; do  # every run has spent its budget (protocol_cpu_hours refuses one that has not)
  [ -d $final2/runs/final2_$variant/trials ] || { echo "switch2.sh: no $final2/runs/final2_$variant/trials"; exit 1; }
done
history=benchmarks/results/history/cpu_float32
mkdir -p $history
for name in learning_final.csv learning_final.md learning_final.png learning_final_readings.csv; do
  git mv benchmarks/results/$name $history/$name
done
python - <<'PY'
path = "benchmarks/final_protocol.py"
text = open(path).read()
for old, new in (
    ("PROTOCOL_SEEDS = (21, 22, 23, 24, 25)", "PROTOCOL_SEEDS = (31, 32, 33, 34, 35)"),
    ("REPLACED_PROTOCOL: tuple[str, tuple[int, ...]] | None = None",
     'REPLACED_PROTOCOL: tuple[str, tuple[int, ...]] | None = ("cpu_float32", (21, 22, 23, 24, 25))'),
):
    assert text.count(old) == 1, f"switch2.sh: {path} does not hold {old!r} once"
    text = text.replace(old, new)
open(path, "w").write(text)
PY
for variant in lstm gru; do
  for seed in 31 32 33 34 35; do
    python benchmarks/learning.py --runs-dir $final2/runs/final2_$variant/trials --variant $variant --seed $seed \
      --protocol-row --torch-threads 1
  done
done
python benchmarks/learning.py --protocol-report --torch-threads 1
git status --short
