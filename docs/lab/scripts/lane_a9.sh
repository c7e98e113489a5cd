#!/bin/bash
# lane_a9.sh (sitting 44, new machine). Lane A: RecurrentPPO 11..13 (each resumes, or skips when done), then their curves.
logs=${LOGS:-/work/logs}
bash $logs/peer_chain.sh "recurrent-ppo 11" "recurrent-ppo 12" "recurrent-ppo 13" >> $logs/peers_b.log 2>&1
