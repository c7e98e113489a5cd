#!/bin/bash
# The two lanes side by side; each step resumes, or skips when done.
logs=${LOGS:-/work/logs}
bash $logs/lane_a12.sh &
bash $logs/lane_b12.sh &
wait
