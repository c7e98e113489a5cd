#!/bin/bash
# usage: curve_rerun.sh 11 12 15   PPO seeds whose snapshots were lost with the machine (2026-12-07): a run of the same
# seed and code (clone $PEERS, daef472) to past 1M env steps, in its own runs dir, then its curve. The row that
# the short run writes goes to a scratch csv, never to benchmarks/results.
peers=${PEERS:-/work/peers}; logs=${LOGS:-/work/logs}
cd $peers || exit 1
mkdir -p $logs/rerun/scratch
for seed in "$@"; do
  done_file=$logs/curve_done_ppo_$seed
  [ -f $done_file ] && continue
  echo "$(date -u) rerun ppo $seed to 1M env steps"
  python benchmarks/ppo_peer.py --algo ppo --seed $seed --cpu-hours 0.85 --runs-dir $peers/runs/curve_rerun \
    --results $logs/rerun/scratch/ppo_peer.csv --first-track 10300 --tracks 30 || exit 1
  echo "$(date -u) curve ppo $seed"
  python benchmarks/ppo_peer.py --algo ppo --seed $seed --curve --runs-dir $peers/runs/curve_rerun \
    --results $logs/rerun/ppo_peer.csv --first-track 10300 --tracks 30 || exit 1
  touch $done_file
done
