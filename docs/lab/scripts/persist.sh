#!/bin/bash
# usage: persist.sh   (at a sitting's end, after the runs are stopped: pkill -f queue_all; pkill -f lane_; pkill -f
# peer_chain; pkill -f curve_rerun; pkill -f ppo_peer.py)
# A machine is not always handed to the next sitting, and a peer run takes more than one sitting (3.1 CPU-hours on
# one thread), so the state a run resumes from is kept in the repository until the run is done: for every peer run
# under $peers/runs whose curve is not done yet, its model.zip, vecnormalize.pkl, record.json and snapshots
# (model_<N>.zip, vecnormalize_<N>.pkl; no TensorBoard logs) go to docs/lab/run_state/<runs subdir>/<run>/, with
# the done-markers and the peer CSVs the clone wrote. restore.sh puts them back on a new machine. A run's state is
# removed from the repository once its row and curve are committed.
set -e
main=${MAIN:-/work/main}
peers=${PEERS:-/work/peers}
logs=${LOGS:-/work/logs}
state=$main/docs/lab/run_state
[ -d $peers/runs ] || { echo "persist.sh: no $peers/runs: nothing to keep (the state kept before is left)"; exit 1; }
rm -rf $state && mkdir -p $state
cd $peers/runs
for run in */*__*; do
  [ -f $run/record.json ] || continue
  base=$(basename $run); variant=${base%__*}; seed=${base##*__}
  algo=$variant; [ "$variant" = recurrent_ppo ] && algo=recurrent-ppo
  [ -f $logs/curve_done_${algo}_${seed} ] && continue
  mkdir -p $state/$run
  cp $run/record.json $run/model.zip $run/vecnormalize.pkl $state/$run/
  cp $run/vecnormalize_*.pkl $state/$run/ 2>/dev/null || true
  for snapshot in $run/model_*.zip; do  # without the optimizer's state (2/3 of the file; restore.sh puts one back)
    [ -f $snapshot ] || continue
    python - $snapshot $state/$snapshot <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as src, zipfile.ZipFile(sys.argv[2], "w", zipfile.ZIP_DEFLATED) as out:
    for name in src.namelist():
        if name != "policy.optimizer.pth":  # (the entry's own date: the same bytes at every stop, one git blob)
            info = zipfile.ZipInfo(name, date_time=src.getinfo(name).date_time)
            info.compress_type = zipfile.ZIP_DEFLATED
            out.writestr(info, src.read(name))
PY
  done
done
mkdir -p $state/lab_logs
cp $logs/curve_done_* $state/lab_logs/ 2>/dev/null || true
cp $peers/benchmarks/results/*peer*.csv $state/lab_logs/ 2>/dev/null || true
[ -f $logs/rerun/ppo_peer_curve.csv ] && cp $logs/rerun/ppo_peer_curve.csv $state/lab_logs/rerun_ppo_peer_curve.csv
du -sh $state
git -C $main status --short --ignored $state | grep '^!!' && { echo "persist.sh: git ignores some of it"; exit 1; }
exit 0
