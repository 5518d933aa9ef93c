#!/bin/bash
# Sequential: one heavy process at a time.
cd "$(dirname "$0")" && . .venv/bin/activate
export MUJOCO_GL=egl WANDB_MODE=disabled PYTHONPATH="$PWD"
for s in 0 1 2; do
  rm -rf runs/seed$s
  echo "seed $s start $(date +%T)"
  timeout -s KILL 480 nice -n 19 python run_lerobot.py $s 4000 runs/seed$s > runs/seed$s.log 2>&1
  echo "seed $s rc=$? end $(date +%T)"
done
