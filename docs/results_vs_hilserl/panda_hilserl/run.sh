#!/bin/bash
# issue 23 item 6: our --method hil-serl on gym-hil's Panda (panda:pick) beside LeRobot's own SAC run
# (docs/results_vs_hilserl/lerobot_check): the same 7 whole-episode takeovers, 45 episodes, seeds 0-2
mkdir -p panda
for s in 0 1 2; do
  nice -n 5 khgrl up --task panda:pick --method hil-serl --takeover episode --episodes 45 \
    --human-episodes 4 5 10 19 20 28 29 --seed $s --run-dir panda/panda_pick-hil-serl_episode-seed$s --no-progress \
    > panda/seed$s.log 2>&1
  echo "seed $s rc=$? $(date +%T)"
done
