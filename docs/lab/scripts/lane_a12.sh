#!/bin/bash
# lane_a12.sh (sitting 48). Lane A: RecurrentPPO 13 to its end, the curves of RecurrentPPO 11..13, then the LSTM's
# runs of the second final protocol (protocol2.sh; it starts only once $logs/protocol2_commit exists, written when
# the bfloat16 screen had passed on both variants and `--amp auto` took it in).
logs=${LOGS:-/work/logs}
bash $logs/peer_chain.sh "recurrent-ppo 11" "recurrent-ppo 12" "recurrent-ppo 13" >> $logs/peers_b.log 2>&1 || exit 1
bash $logs/protocol2.sh lstm >> $logs/final2_lstm.log 2>&1
