#!/bin/bash
bash /work/logs/lane_a9.sh &
bash /work/logs/lane_b9.sh &
wait
