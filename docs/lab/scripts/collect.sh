#!/bin/bash
# usage: collect.sh   the peers' finished rows and curves on the report tracks 10300..10329 (the clone's CSVs, and the
# re-run curves) into main's benchmarks/results, each seed's rows replacing that seed's earlier ones there
# (ppo_peer.write_rows); then the report. Commit what it changed.
main=${MAIN:-/work/main}; peers=${PEERS:-/work/peers}; logs=${LOGS:-/work/logs}
cd $main || exit 1
python - $peers/benchmarks/results $logs/rerun <<'PY' || exit 1
import os, sys
sys.path.insert(0, "benchmarks")
import ppo_peer

sources = sys.argv[1:]
for name in ("ppo_peer.csv", "recurrent_ppo_peer.csv", "ppo_peer_curve.csv", "recurrent_ppo_peer_curve.csv"):
    columns = ppo_peer.CURVE_COLUMNS if name.endswith("_curve.csv") else ppo_peer.COLUMNS
    for source in sources:
        path = os.path.join(source, name)
        if not os.path.exists(path):
            continue
        rows = [r for r in ppo_peer.read_rows(path) if r["tracks"] == "10300..10329"]
        for seed in sorted({r["seed"] for r in rows}):
            mine = [r for r in rows if r["seed"] == seed]
            ppo_peer.write_rows(mine, os.path.join("benchmarks", "results", name), columns)
            print(f"{name}: seed {seed}, {len(mine)} row(s) from {source}")
PY
python benchmarks/learning.py --protocol-report --results-dir benchmarks/results --torch-threads 1 > /dev/null || exit 1
git -C $main status --short benchmarks/results
