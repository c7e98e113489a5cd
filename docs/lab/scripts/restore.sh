#!/bin/bash
# usage: restore.sh   on a new machine (no $peers): the clone of the peers' code, the lab scripts, and every
# run's state that persist.sh kept, then `nohup $logs/queue_all12.sh > $logs/queue_all.log 2>&1 &`.
set -e
main=${MAIN:-/work/main}
peers=${PEERS:-/work/peers}
logs=${LOGS:-/work/logs}
state=$main/docs/lab/run_state
[ -d $peers ] && { echo "restore.sh: $peers exists (not a new machine): nothing restored"; exit 1; }
git clone -q $main $peers && git -C $peers checkout -q daef472
mkdir -p $logs/rerun/scratch $peers/runs
cp $main/docs/lab/scripts/*.sh $main/docs/lab/scripts/*.py $logs/ && chmod +x $logs/*.sh
# the second final protocol's code (fixed 2026-12-07; docs/lab/final_protocol.md): protocol2.sh runs nothing without it
[ -f $logs/protocol2_commit ] || git -C $main rev-parse 9ee7f0e > $logs/protocol2_commit
[ -d $state ] || exit 0
for run in $(cd $state && ls -d */*__* 2>/dev/null); do
  mkdir -p $peers/runs/$run && cp $state/$run/* $peers/runs/$run/
  for snapshot in $peers/runs/$run/model_*.zip; do  # SB3's load wants an optimizer state: the run's current one
    [ -f $snapshot ] || continue
    python - $snapshot $peers/runs/$run/model.zip <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as snapshot:
    missing = "policy.optimizer.pth" not in snapshot.namelist()
if missing:
    with zipfile.ZipFile(sys.argv[2]) as model, zipfile.ZipFile(sys.argv[1], "a", zipfile.ZIP_DEFLATED) as out:
        out.writestr("policy.optimizer.pth", model.read("policy.optimizer.pth"))
PY
  done
done
cp $state/lab_logs/curve_done_* $logs/ 2>/dev/null || true
for f in $state/lab_logs/*peer*.csv; do
  [ -f "$f" ] || continue
  case $(basename $f) in
    rerun_ppo_peer_curve.csv) cp $f $logs/rerun/ppo_peer_curve.csv ;;
    *) cp $f $peers/benchmarks/results/ ;;
  esac
done
echo "restored: $(cd $state && ls -d */*__* 2>/dev/null | tr '\n' ' ')"
