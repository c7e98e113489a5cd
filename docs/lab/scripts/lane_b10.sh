#!/bin/bash
# lane_b10.sh (sitting 46). Lane B: PPO 13 (resumes, or skips when done) and its curve; then the bfloat16 screen on the
# LSTM (seed 11 fits in a sitting, and a screen's replays cannot move to another machine, the peers' state can); then
# PPO 14 and its curve.
logs=${LOGS:-/work/logs}
while pgrep -f "ppo_peer.py --algo ppo --seed 13 " > /dev/null; do sleep 30; done  # a PPO 13 started by lane_b9.sh
bash $logs/peer_chain.sh "ppo 13" >> $logs/peers_a.log 2>&1 || exit 1
bash $logs/screen_chain.sh amp "amp=on" "--cpu-hours 1.06" "--cpu-hours 1.06" || exit 1
bash $logs/peer_chain.sh "ppo 13" "ppo 14" >> $logs/peers_a.log 2>&1
