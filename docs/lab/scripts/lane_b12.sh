#!/bin/bash
# lane_b12.sh (sitting 48). Lane B: the bfloat16 screen's GRU seed 12 (`gruamp12`, started by lane_b11.sh) to its
# end and report (skipped once reported), then PPO 14 and its curve, then the GRU's runs of the second final
# protocol (protocol2.sh, as in lane_a12.sh).
logs=${LOGS:-/work/logs}
while pgrep -f "sweep.py --name gruamp12 " > /dev/null; do sleep 30; done  # (started by lane_b11.sh)
VARIANTS=gru bash $logs/screen_chain.sh gruamp "amp=on" "--cpu-hours 1.11" "--cpu-hours 1.11" || exit 1
python $logs/screen_judge.py gruamp gru >> $logs/sweep_gruamp12.log 2>&1
bash $logs/peer_chain.sh "ppo 13" "ppo 14" >> $logs/peers_a.log 2>&1 || exit 1
bash $logs/protocol2.sh gru >> $logs/final2_gru.log 2>&1
