import csv
import glob
import re

for d in sorted(glob.glob("runs/seed*/")):
    s = d.rstrip("/").split("seed")[-1]
    rows = list(csv.DictReader(open(d + "episodes.csv")))
    log = open(f"runs/seed{s}.log").read()
    nopt = log.count("Optimization frequency loop")
    m = re.search(r"DONE seed=\d+ steps=(\d+) wall_s=([\d.]+)", log)
    print(f"## seed {s}: episodes={len(rows)} env_steps={rows[-1]['total_steps'] if rows else 0} "
          f"learner_grad_steps={nopt} done={m.group(0) if m else 'NOT FINISHED'}")
    print("episode:success(intervened) list:")
    print(" ".join(f"{r['episode']}:{r['success']}{'(I)' if int(r['intervened_steps']) else ''}" for r in rows))
    print("per block of 10 episodes: [episodes] succ/10 (non-intervened succ / non-intervened n), mean ep_len, "
          "env steps at block end")
    for i in range(0, len(rows), 10):
        b = rows[i:i+10]
        ni = [r for r in b if int(r["intervened_steps"]) == 0]
        print(f"  ep {b[0]['episode']}-{b[-1]['episode']}: {sum(int(r['success']) for r in b)}/{len(b)} "
              f"(autonomous {sum(int(r['success']) for r in ni)}/{len(ni)}), "
              f"len {sum(int(r['ep_len']) for r in b) / len(b):.1f}, "
              f"steps {b[-1]['total_steps']}, wall {b[-1]['wall_s']}s")
