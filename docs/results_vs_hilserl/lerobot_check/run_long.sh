#!/bin/bash
cd "$(dirname "$0")" && . .venv/bin/activate
export MUJOCO_GL=egl WANDB_MODE=disabled PYTHONPATH="$PWD"
rm -rf runs/seed3
echo "seed 3 start $(date +%T)"
timeout -s KILL 540 nice -n 19 python run_lerobot.py 3 12000 runs/seed3 > runs/seed3.log 2>&1
echo "seed 3 rc=$? end $(date +%T)"
