#!/bin/bash
# usage: peer_chain.sh "ppo 11" "ppo 12" ...   trains each peer (skipping one with a report-track row), then its curve
peers=${PEERS:-/work/peers}; logs=${LOGS:-/work/logs}
cd $peers || exit 1
items=("$@")
for item in "${items[@]}"; do
  read -r algo seed <<< "$item"
  csv=benchmarks/results/ppo_peer.csv; [ "$algo" = recurrent-ppo ] && csv=benchmarks/results/recurrent_ppo_peer.csv
  if [ -f $csv ] && python - "$csv" "$seed" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
sys.exit(0 if any(r.get("seed") == sys.argv[2] and r.get("tracks") == "10300..10329" for r in rows) else 1)
PY
  then echo "$(date -u) $algo $seed has its row"; else
    echo "$(date -u) train $algo $seed"
    python benchmarks/ppo_peer.py --algo $algo --seed $seed --cpu-hours 3.1 --first-track 10300 --tracks 30 || exit 1
  fi
done
for item in "${items[@]}"; do
  read -r algo seed <<< "$item"
  done_file=$logs/curve_done_${algo}_${seed}
  [ -f $done_file ] && continue
  echo "$(date -u) curve $algo $seed"
  python benchmarks/ppo_peer.py --algo $algo --seed $seed --curve --first-track 10300 --tracks 30 || exit 1
  touch $done_file
done
