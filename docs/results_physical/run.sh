#!/bin/bash
# Physical corrections vs the drag on gym-hil's Panda (docs/results_physical.md). From the repository root:
#   bash docs/results_physical/run.sh runs/physical      # 6 runs of khgrl up, one after another (~3 min each here)
#   SEEDS="4 5 6" ARMS=physical bash docs/results_physical/run.sh runs/physical2   # the second measurement
#   python docs/results_physical/analyze.py runs/physical --out docs/results_physical
set -euo pipefail
out=${1:-runs/physical}
seeds=${SEEDS:-1 2 3}
arms=${ARMS:-drag physical}
common=(--task panda:pick --no-adapt --method khgrl --episodes 30 --human-episodes 4 5 10 19 20
        --rate-limit on --max-speed 1 --no-progress)
for seed in $seeds; do
  for arm in $arms; do
    dir=$out/panda_pick-$arm-seed$seed
    if [ -f "$dir/summary.json" ] && grep -q '"failed": \[\]' "$dir/summary.json"; then continue; fi
    rm -rf "$dir"
    if [ $arm = drag ]; then extra=(--human scripted); else extra=(--physical scripted --human none); fi
    khgrl up "${common[@]}" "${extra[@]}" --seed $seed --run-dir "$dir" > "$out/$arm-$seed.log" 2>&1 || true
    echo "$arm seed $seed: $(tail -1 "$out/$arm-$seed.log")"
  done
done
