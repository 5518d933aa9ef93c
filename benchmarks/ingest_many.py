"""Ingest from many senders into one learner (``khgrl bench ingest``): S sender processes, each a stand-in actor
with its own id publishing valid transition batches (encoded before timing) with at most ``window`` batches
unacknowledged, into one real learner (which never trains: ``--learning-starts`` above the total). Reported:
transitions per second the learner acknowledged, from the first batch published to the last ack (wall clock,
all processes on this machine), the learner's memory and the machine's load.

    khgrl bench ingest --senders 8 --transitions 400000 --batch 256
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["run_ingest_benchmark", "sender_main"]

REPO = Path(__file__).resolve().parents[1]


def sender_main(argv: list[str]) -> int:
    """One sender process: ``ENDPOINT RUN ACTOR N BATCH WINDOW SEED``; prints a JSON line with its times."""
    import numpy as np
    from khgrl.benchmarks.runtime.link import batches
    from khgrl.common.delivery.declare import alive_now, publisher, subscribe
    from khgrl.common.delivery.transport import Inbox, open_client
    from khgrl.common.wire.messages import Ack
    from khgrl.common.wire.protocol import Keys, ProtocolError, decode, encode

    endpoint, run, actor = argv[0], argv[1], argv[2]
    n, batch, window, seed = (int(x) for x in argv[3:7])
    payloads = [_as_actor(p, actor, decode, encode) for p in batches(n, batch, seed)]
    keys, acks = Keys(run), Inbox(maxsize=100_000)
    with open_client(endpoint, timeout=30) as session:
        sub = subscribe(session, keys.ack(actor), acks.callback("ack"))
        pub = publisher(session, keys.transitions(actor), congestion="block")
        while not alive_now(session, keys.learners_alive, timeout=1.0):
            time.sleep(0.2)
        time.sleep(0.5)
        print(json.dumps({"ready": actor}), flush=True)
        sys.stdin.readline()  # all senders start together
        received, nxt, last = -1, 0, len(payloads) - 1
        t0 = time.time()
        t_last = stall = time.monotonic()
        while received < last:
            while nxt <= last and nxt - 1 - received < window:
                pub.put(payloads[nxt])
                nxt += 1
            item = acks.get(0.5)
            while item is not None:
                try:
                    received = max(received, decode(Ack, item[2]).received)
                    stall = time.monotonic()
                except ProtocolError:
                    pass
                item = acks.get()
            if time.monotonic() - stall > 5.0:  # lost before the subscription matched: the window again
                nxt, stall = received + 1, time.monotonic()
            t_last = time.time()
        sub.undeclare()
        pub.undeclare()
    print(json.dumps({"actor": actor, "start": t0, "end": t_last, "transitions": n,
                      "batches": int(np.ceil(n / batch))}), flush=True)
    return 0


def _as_actor(payload: bytes, actor: str, decode, encode) -> bytes:
    from khgrl.common.wire.messages import Transitions

    msg = decode(Transitions, payload)
    return encode(msg.replace(actor=actor), actor, msg.envelope.seq)


def _secure_files(work_dir: Path, ep: str, senders: int) -> dict[str, Path]:
    """A CA, certificates for the router, the learner and each sender, and their Zenoh configurations."""
    from khgrl.deploy.run.secure import issue_identities, write_configs

    ids = [("router", None), ("learner", None), *(("actor", f"s{i}") for i in range(senders))]
    d = issue_identities(work_dir / f"certs-{os.getpid()}-{time.time_ns()}", ids)
    return write_configs(d, ep, ep)


def run_ingest_benchmark(senders: int = 8, transitions: int = 400_000, batch: int = 256, window: int = 16,
                         seed: int = 0, work: str = "runs/bench-ingest", out: str | None = None,
                         secure: bool = False) -> dict:
    """Start a router, a learner and ``senders`` sender processes; return (and print) the ingest rate.

    :param senders: sender processes (actor ids s0, s1, ...)
    :param transitions: transitions in all (split evenly)
    :param batch: transitions per batch
    :param window: unacknowledged batches per sender at most
    :param seed: seed of the contents
    :param work: run directory of the learner
    :param out: also write the result as JSON here
    :param secure: mutual TLS and access control (as ``khgrl up --secure``) instead of plain TCP
    """
    from khgrl.benchmarks.runtime.procs import BenchProcs, run_id
    from khgrl.common.delivery.transport import free_port, wait_reachable

    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    procs, run, ep = BenchProcs(work_dir), run_id("ingest"), f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
    files = _secure_files(work_dir, ep, senders) if secure else {}
    zargs = lambda cn: ["--zenoh-config", str(files[cn])] if secure else []  # noqa: E731
    procs.start("router", "router", "--listen", ep, *zargs("router"))
    wait_reachable(ep, 30.0)
    learner = procs.learner("learner", run, ep, work_dir / run, "--learning-starts", str(10 * transitions),
                            "--checkpoint-every", "0", *zargs("learner"))
    each = transitions // senders
    code = "import sys; from khgrl.benchmarks.ingest_many import sender_main; sys.exit(sender_main(sys.argv[1:]))"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    envs = [{**env, "ZENOH_CONFIG": str(files[f"actor-s{i}"])} if secure else env for i in range(senders)]
    ps = [subprocess.Popen([sys.executable, "-c", code, ep, run, f"s{i}", str(each), str(batch), str(window),
                            str(seed + i)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=envs[i],
                           cwd=REPO) for i in range(senders)]
    try:
        for p in ps:
            json.loads(p.stdout.readline())  # ready
        load0 = os.getloadavg()
        for p in ps:
            p.stdin.write("go\n")
            p.stdin.flush()
        done = [json.loads(p.stdout.readline()) for p in ps]
        for p in ps:
            p.wait(60)
    finally:
        for p in ps:
            if p.poll() is None:
                p.kill()
        learner.stop(60.0)
        procs.close()
    elapsed = max(d["end"] for d in done) - min(d["start"] for d in done)
    res = {"transport": "mtls" if secure else "tcp", "senders": senders, "transitions": each * senders,
           "batch": batch, "window": window,
           "elapsed_s": round(elapsed, 3), "transitions_per_s": round(each * senders / elapsed, 1),
           "load_before": [round(x, 2) for x in load0], "load_after": [round(x, 2) for x in os.getloadavg()],
           "cpus": os.cpu_count()}
    print(f"{res['transport']}: {senders} senders -> 1 learner: {res['transitions']} transitions in {elapsed:.2f} s = "
          f"{res['transitions_per_s']:.0f} transitions/s (batch {batch}, window {window}; load {res['load_before']})")
    if out:
        Path(out).write_text(json.dumps(res, indent=2))
    return res
