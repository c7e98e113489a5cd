#!/bin/bash
# lane_a11.sh (sitting 47). Lane A: the terminal-weight screen (its LSTM seed 12, `terminal12`, that lane_a10.sh
# started, to its end and report); if the LSTM passes rules 1-3 (screen_judge.py), its GRU part (seeds 11, 12 at
# 4,200 updates, as fixed in docs/lab/screens.md) before the peers, because a screen cannot move to another machine
# and a peer's state can; then RecurrentPPO 13 and the curves of RecurrentPPO 11..13.
logs=${LOGS:-/work/logs}
while pgrep -f "sweep.py --name terminal12 " > /dev/null; do sleep 30; done  # (started by lane_a10.sh)
bash $logs/screen_chain.sh terminal "terminal_weight=10" "--updates 5100" "--updates 5400" || exit 1
if python $logs/screen_judge.py terminal lstm >> $logs/sweep_terminal12.log 2>&1; then
  VARIANTS=gru bash $logs/screen_chain.sh gruterminal "terminal_weight=10" "--updates 4200" "--updates 4200" || exit 1
fi
bash $logs/peer_chain.sh "recurrent-ppo 11" "recurrent-ppo 12" "recurrent-ppo 13" >> $logs/peers_b.log 2>&1
