#!/bin/bash
# lane_a10.sh (sitting 46). Lane A: the RecurrentPPO 12 that lane_a9.sh started, to its end; then the terminal-weight
# screen on the LSTM (seed 11 fits in a sitting, and a screen's replays cannot move to another machine, the peers'
# state can); then RecurrentPPO 12 (if unfinished) and 13, and the curves of RecurrentPPO 11..13.
logs=${LOGS:-/work/logs}
while pgrep -f "ppo_peer.py --algo recurrent-ppo --seed 12 " > /dev/null; do sleep 30; done
bash $logs/screen_chain.sh terminal "terminal_weight=10" "--updates 5100" "--updates 5400" || exit 1
bash $logs/peer_chain.sh "recurrent-ppo 11" "recurrent-ppo 12" "recurrent-ppo 13" >> $logs/peers_b.log 2>&1
