#!/bin/bash
# lane_b11.sh (sitting 47). Lane B: the bfloat16 screen (its LSTM seed 12, `amp12`, that lane_b10.sh started, to
# its end and report); if the LSTM passes rules 1-3 (screen_judge.py), its GRU part (seeds 11, 12 at 1.11
# CPU-hours, as fixed in docs/lab/screens.md) before the peers, because a screen cannot move to another machine and
# a peer's state can; then PPO 14 and its curve.
logs=${LOGS:-/work/logs}
while pgrep -f "sweep.py --name amp12 " > /dev/null; do sleep 30; done  # (started by lane_b10.sh)
bash $logs/screen_chain.sh amp "amp=on" "--cpu-hours 1.06" "--cpu-hours 1.06" || exit 1
if python $logs/screen_judge.py amp lstm >> $logs/sweep_amp12.log 2>&1; then
  VARIANTS=gru bash $logs/screen_chain.sh gruamp "amp=on" "--cpu-hours 1.11" "--cpu-hours 1.11" || exit 1
fi
bash $logs/peer_chain.sh "ppo 13" "ppo 14" >> $logs/peers_a.log 2>&1
