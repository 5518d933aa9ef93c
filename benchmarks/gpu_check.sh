#!/usr/bin/env bash
# The learner's GPU checks in one script of at most about 5 minutes, for a machine with an NVIDIA GPU, torch with
# CUDA and Python 3.12 but no network: the project and the packages the machine lacks come as wheels.
#
#   benchmarks/gpu_check.sh WHEEL_DIR OUT_DIR
#
# WHEEL_DIR: khgrl's wheel (pip wheel --no-deps .) and those of stable-baselines3, sb3-contrib, gymnasium,
# farama-notifications, eclipse-zenoh, cryptography, cffi, pycparser, dill (pip download --no-deps
# --only-binary=:all: --python-version 3.12 ...). Writes under OUT_DIR: gpu.txt (nvidia-smi), gpu_check.json (the
# graphed step's correctness, khgrl.benchmarks.gpu_check), bench_learner.json (khgrl bench learner --devices cpu
# cuda) and bench_scale.json (khgrl bench scale --actors 1 8 14, the learner on cuda), each with its log.
set -u
WHEELS=$(cd "${1:?wheel folder}" && pwd); OUT=$(mkdir -p "${2:?output folder}" && cd "$2" && pwd)
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/khgrl-site \
    "$WHEELS"/*.whl || exit 1
export PYTHONPATH=/tmp/khgrl-site${PYTHONPATH:+:$PYTHONPATH}
cd /tmp || exit 1  # (not a checkout's root: its khgrl/ folder would shadow the installed package)
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; } > "$OUT/gpu.txt" 2>&1
timeout 60 python3 -m khgrl.benchmarks.gpu_check --device cuda --out "$OUT/gpu_check.json" > "$OUT/gpu_check.log" 2>&1
echo "gpu_check rc=$?"; tail -c 1500 "$OUT/gpu_check.log"
timeout 90 python3 -m khgrl.deploy.cli bench learner --devices cpu cuda --seconds 3 \
    --out "$OUT/bench_learner.json" > "$OUT/bench_learner.log" 2>&1
echo "bench learner rc=$?"; grep -v "^wrote" "$OUT/bench_learner.log" | tail -c 2500
timeout 150 python3 -m khgrl.deploy.cli bench scale --actors 1 8 14 --rates 0 --modes simulation --seconds 10 \
    --device cuda --work /tmp/khgrl-scale --out "$OUT/bench_scale.json" > "$OUT/bench_scale.log" 2>&1
echo "bench scale rc=$?"; tail -c 2500 "$OUT/bench_scale.log"
