#!/bin/bash
# usage: restore.sh   on a new machine (no /work/peers): the clone of the peers' code, the lab scripts, and every
# run's state that persist.sh kept, then `nohup /work/logs/queue_all9.sh > /work/logs/queue_all.log 2>&1 &`.
set -e
main=/work/main
state=$main/docs/lab/run_state
[ -d /work/peers ] || { git clone -q $main /work/peers && git -C /work/peers checkout -q daef472; }
mkdir -p /work/logs/rerun/scratch /work/peers/runs
cp $main/docs/lab/scripts/*.sh /work/logs/ && chmod +x /work/logs/*.sh
[ -d $state ] || exit 0
for run in $(cd $state && ls -d */*__* 2>/dev/null); do
  mkdir -p /work/peers/runs/$run && cp $state/$run/* /work/peers/runs/$run/
done
cp $state/logs/curve_done_* /work/logs/ 2>/dev/null || true
for f in $state/logs/*peer*.csv; do
  [ -f "$f" ] || continue
  case $(basename $f) in
    rerun_ppo_peer_curve.csv) cp $f /work/logs/rerun/ppo_peer_curve.csv ;;
    *) cp $f /work/peers/benchmarks/results/ ;;
  esac
done
echo "restored: $(cd $state && ls -d */*__* 2>/dev/null | tr '\n' ' ')"
