#!/bin/bash
# lane_b9.sh (sitting 44, new machine). Lane B: the curves of PPO 11, 12, 15 from re-runs to 1M env steps, then PPO 13,
# 14 and their curves.
logs=${LOGS:-/work/logs}
bash $logs/curve_rerun.sh 11 12 15 >> $logs/peers_a.log 2>&1 || exit 1
bash $logs/peer_chain.sh "ppo 13" "ppo 14" >> $logs/peers_a.log 2>&1
