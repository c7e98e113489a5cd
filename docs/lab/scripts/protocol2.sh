#!/bin/bash
# usage: protocol2.sh VARIANT   the second final protocol's runs of one variant, one trial at a time on one core:
# seeds 31..35 at 3.1 CPU-hours, the CPU preset at --amp auto (bfloat16 on this CPU), as docs/lab/screens.md
# ("What the screens' passes lead to", point 2) fixed. Code: a clone of main (/work/final2) at the commit in
# $logs/protocol2_commit (written when the bfloat16 screen passed on both variants; without it nothing runs).
# Each variant is its own Ray Tune experiment (storage runs/final2_VARIANT), so that each lane runs one; a trial
# resumes where it stopped, on this machine only (its replay is not kept in git).
logs=${LOGS:-/work/logs}; dir=${FINAL2:-/work/final2}; variant=$1
[ -f $logs/protocol2_commit ] || { echo "$(date -u) protocol2: no $logs/protocol2_commit: not started"; exit 0; }
commit=$(cat $logs/protocol2_commit)
(
  flock 9
  if [ ! -d $dir ]; then
    rm -rf $dir.tmp
    git clone -q ${MAIN:-/work/main} $dir.tmp && git -C $dir.tmp checkout -q $commit && mv $dir.tmp $dir || exit 1
  fi
) 9> $logs/final2.lock || exit 1
cd $dir && [ "$(git rev-parse HEAD)" = "$(git rev-parse $commit)" ] || { echo "protocol2: $dir is not at $commit"; exit 1; }
echo "$(date -u) protocol2 $variant (seeds 31..35) from $commit"
python benchmarks/experiment.py --stages single --single-cpu-hours 3.1 --seeds 31 32 33 34 35 --variants $variant \
  --storage runs/final2_$variant --results runs/final2_$variant --num-cpus 1
