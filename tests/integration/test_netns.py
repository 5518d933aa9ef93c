"""The system across a real network: router, learner, actor and the scripted human each in a Linux network
namespace of its own (tests/netns.py: veth links to a bridge in a switch namespace, private addresses), set up as
README's "Running across machines" says: certificates from ``khgrl certs`` (the router's naming the router
namespace's address), the configurations ``khgrl certs configs`` writes (mutual TLS, access control per identity),
every process a Zenoh client of ``tls/<router address>:7447`` with its own identity. Nothing is restarted while the
network misbehaves:

1. warm-up: the actor finishes its first episode (the scripted human, in its own namespace, corrects it);
2. 5 % packet loss (nftables, in and out) on the actor's and the learner's links for ``LOSS_S`` seconds;
3. the actor's link down for ``OUTAGE_S`` = 10 s (loss still on), then up again;
4. recovery (loss still on) until the learner holds what the actor made during the outage, then loss off;
5. a clean stop: SIGINT to the actor, the human, the learner (last but the router: its final checkpoint).

Checked: the actor kept acting while its link was down (its outbox on disk grew: every batch is written there
before it is published), it reconnected by itself (time from link up to the learner acknowledging a new batch
from it, and to its liveliness token being back, measured by a monitor client in the router's namespace), and
every transition it made is in the learner's final checkpoint exactly once (khgrl.benchmarks.scale.provenance_check).
A second actor, a1, on a healthy link, must keep streaming while a0's link is down: one robot losing its network
must not stall the others (with the router's built-in settings it did -- docs/netns.md, "The router stall").

The measured numbers are printed (``pytest -s`` shows them); docs/netns.md has a run. Skipped (with the reason)
only where namespaces cannot be made: not root, no ``ip``/``nft``, or not permitted.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import sys
import time
from pathlib import Path

import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for
from netns import Network, netns_available

PORT = 7447  # every namespace has its own ports: no clash with anything on the host
LOSS = 5  # percent, each direction
LOSS_S = 15.0  # seconds of loss before the outage
OUTAGE_S = 10.0
RATE = 50.0  # Hz: the actors' control rate (an outage of 10 s is ~500 steps, ~62 batches)
ACTORS = ("a0", "a1")  # a0 goes through the outage; a1's link stays healthy
ROLES = ("router", "learner", "human", *ACTORS)
THIS = Path(__file__).resolve()


# ----------------------------------------------------------------------------------------- the monitor process
def monitor_main(argv: list[str]) -> int:
    """A Zenoh client that writes what it sees of run ``RUN`` to ``OUT`` as JSON lines: acks, status and
    liveliness changes, each with the wall-clock time of arrival (``t``; every namespace shares the clock).

    argv: ENDPOINT RUN OUT ZENOH_CONFIG
    """
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.process import StopFlag, install_stop_handlers
    from khgrl.common.wire.messages import Ack, Status
    from khgrl.common.wire.protocol import Keys, decode

    endpoint, run, out, zenoh_config = argv
    flag = StopFlag()
    install_stop_handlers(flag)
    keys = Keys(run)
    with open(out, "a") as fh, open_client(endpoint, stop=lambda: bool(flag), zenoh_config=zenoh_config) as session:
        subs = [("ack", session.declare_subscriber(keys.ack())), ("status", session.declare_subscriber(keys.status())),
                ("alive", session.liveliness().declare_subscriber(keys.alive(), history=True))]
        fh.write(json.dumps({"t": time.time(), "kind": "open"}) + "\n")
        fh.flush()
        while not flag:
            n = 0
            for kind, sub in subs:
                while (s := sub.try_recv()) is not None:
                    n += 1
                    rec = {"t": time.time(), "kind": kind, "key": str(s.key_expr)}
                    if kind == "ack":
                        rec.update(dataclasses.asdict(decode(Ack, s.payload.to_bytes())))
                    elif kind == "status":
                        st = decode(Status, s.payload.to_bytes())
                        rec.update(role=st.role, info=dataclasses.asdict(st.info))
                    else:
                        rec["put"] = str(s.kind).upper().endswith("PUT")
                    fh.write(json.dumps(rec, default=str) + "\n")
            fh.flush()
            if not n:
                time.sleep(0.01)
        for _, sub in subs:
            sub.undeclare()
    return 0


class Seen:
    """What the monitor wrote so far (re-read on every call)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def records(self, kind: str) -> list[dict]:
        if not self.path.is_file():
            return []
        out = []
        for line in self.path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:  # (a line being written)
                continue
            if rec["kind"] == kind:
                out.append(rec)
        return out

    def acks(self, actor: str) -> list[dict]:
        return [r for r in self.records("ack") if r["actor"] == actor and r.get("epoch")]

    def received(self, actor: str, before: float = float("inf")) -> int:
        """The highest ``received`` of ``actor``'s acks that arrived before ``before`` (-1: none)."""
        return max([r["received"] for r in self.acks(actor) if r["t"] < before], default=-1)

    def status(self, role: str, ident: str) -> list[dict]:
        return [r for r in self.records("status") if r["key"].endswith(f"/status/{role}/{ident}")]

    def alive(self, role: str, ident: str) -> list[tuple[float, bool]]:
        return [(r["t"], r["put"]) for r in self.records("alive") if f"/alive/{role}/{ident}/" in r["key"] + "/"]


# ----------------------------------------------------------------------------------------- helpers
def _write_run(run_dir: Path, run: str, endpoint: str) -> Path:
    """``RUN_DIR/config.json`` and the learner's task file, as ``khgrl up`` writes them; returns config.json."""
    from khgrl.common.config.settings import RunConfig, SafetySettings, StreamSettings, TQCSettings, write_run_config
    from khgrl.common.delivery.task_link import TASK_FILE, save_task
    from khgrl.deploy.run.preflight import check_task

    cfg = RunConfig(scenario="low_cov", method="khgrl", episodes=1000, seed=0, run_dir=str(run_dir), run=run,
                    actors=len(ACTORS), human="scripted", human_episodes=(1,), connect=endpoint, rate=RATE,
                    tensorboard=False,
                    tqc=TQCSettings(learning_starts=400, net_arch=(64, 64), batch_size=64),
                    stream=StreamSettings(mode="robot", checkpoint_every=800),
                    # delivery across partitions is this test's: supervision, which holds the robot on a partition, is
                    # tests/integration/test_supervision.py's
                    safety=SafetySettings(supervision="off")).validate()
    path = write_run_config(run_dir, cfg, {"run": run, "endpoint": endpoint, "actor_ids": list(ACTORS),
                                           "argv": ["tests/integration/test_netns.py"], "resumed": False, "part": 1})
    save_task(run_dir / "learner" / TASK_FILE, check_task(cfg))
    return path


def _certificates(d: Path, router_addr: str, endpoint: str) -> dict[str, Path]:
    """A CA, the router's certificate for its address and one per process, and every Zenoh configuration (the
    README's steps 1-2): {common name: configuration file}."""
    from khgrl.deploy.run.secure import issue_identities, write_configs

    ids = [("router", None), ("learner", None), ("human", "scripted"), ("monitor", None),
           *(("actor", a) for a in ACTORS)]
    issue_identities(d, ids, router_hosts=(router_addr,))
    return write_configs(d, f"tls/{router_addr}:{PORT}", endpoint)


def _newest_batch(actor_dir: Path) -> int:
    """The highest batch seq in the actor's outbox on disk (-1: none)."""
    seqs = [int(p.stem) for p in (actor_dir / "outbox").glob("*.msgpack") if p.stem.isdigit()]
    return max(seqs, default=-1)


@pytest.fixture
def net():
    reason = netns_available()
    if reason:
        pytest.skip(f"network namespaces: {reason}")
    with Network(ROLES) as network:
        yield network


# ----------------------------------------------------------------------------------------- the test
@pytest.mark.integration
@pytest.mark.timeout(420)
def test_loss_and_a_10s_outage_lose_nothing_and_the_actor_reconnects(net, tmp_path):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.deploy.run.supervisor import khgrl_argv

    t_start = time.monotonic()
    run, run_dir = unique_run("netns"), tmp_path / "run"
    endpoint = f"tls/{net.addr('router')}:{PORT}"
    config = str(_write_run(run_dir, run, endpoint))
    zc = {cn: ["--zenoh-config", str(p)] for cn, p in _certificates(tmp_path / "certs", net.addr("router"),
                                                                    endpoint).items()}
    seen = Seen(tmp_path / "monitor.jsonl")
    out = {a: run_dir / f"actor-{a}" for a in ACTORS}
    with ProcGroup(tmp_path) as g:
        def start(role: str, name: str, argv: list[str]):
            return g.start(name, net.argv(role, argv))

        router = start("router", "router", khgrl_argv("router", *zc["router"], "--listen", endpoint))
        wait_for(lambda: "listening on" in router.text(), 60, "the router", procs=[router])
        monitor = start("router", "monitor", [sys.executable, "-c", (
            f"import sys; sys.path[:0] = [{str(THIS.parent)!r}, {str(THIS.parents[1])!r}]; "
            f"from test_netns import monitor_main; sys.exit(monitor_main(sys.argv[1:]))"),
            endpoint, run, str(seen.path), zc["monitor"][1]])
        learner = start("learner", "learner", khgrl_argv("learner", "--config", config, "--connect", endpoint,
                                                         *zc["learner"]))
        human = start("human", "human", khgrl_argv("human", "scripted", "--config", config, "--connect", endpoint,
                                                   *zc["human-scripted"]))
        actors = {a: start(a, a, khgrl_argv("actor", "--config", config, "--id", a, "--connect", endpoint,
                                            *zc[f"actor-{a}"])) for a in ACTORS}
        procs = [router, monitor, learner, human, *actors.values()]
        wait_for(lambda: seen.records("open"), 60, "the monitor", procs=procs)

        # 1. warm-up: a0's first episode (the human's) done, the learner acknowledging both actors
        wait_for(lambda: (out["a0"] / "episodes.csv").is_file()
                 and len((out["a0"] / "episodes.csv").read_text().splitlines()) >= 2, 180, "a0's first episode",
                 procs=procs)
        wait_for(lambda: all(seen.received(a) >= 0 for a in ACTORS), 60, "acks for every actor", procs=procs)
        t_warm = time.monotonic()

        # 2. loss on the actor's and the learner's links
        r0 = seen.received("a0")
        net.set_loss("a0", LOSS)
        net.set_loss("learner", LOSS)
        time.sleep(LOSS_S)
        r1 = seen.received("a0")
        assert r1 > r0, f"no batch of a0 got through {LOSS} % loss in {LOSS_S:g} s ({r0} -> {r1})"

        # 3. the outage: a0 keeps acting (its outbox grows), then its link comes back
        newest_down = max(_newest_batch(out["a0"]), seen.received("a0"))
        net.link_down("a0")
        t_down = time.time()
        time.sleep(OUTAGE_S)
        newest_up = _newest_batch(out["a0"])
        assert actors["a0"].poll() is None, actors["a0"].tail()
        net.link_up("a0")
        t_up = time.time()
        made = newest_up - newest_down
        assert made >= 10, f"a0 made {made} batches while its link was down for {OUTAGE_S:g} s: it did not keep acting"
        # a1's link is fine: once the router has given a0 up (its lease), a1's batches keep reaching the learner
        a1_during = seen.received("a1", before=t_up) - seen.received("a1", before=t_down + 4.0)
        assert a1_during >= 10, (f"a1 had {a1_during} batches acknowledged while a0's link was down: a0's outage "
                                 f"stalled the others (router log:\n{router.tail()})")

        # 4. recovery (loss still on): the learner acknowledges a0's new batches, then everything of the outage
        before = seen.received("a0", before=t_up)
        first = wait_for(lambda: next((r for r in seen.acks("a0") if r["t"] >= t_up and r["received"] > before),
                                      None), 120, "a new batch of a0 after the link came up", procs=procs)
        reconnect_s = first["t"] - t_up
        wait_for(lambda: seen.received("a0") >= newest_up, 120, "the learner holding a0's outage batches",
                 procs=procs)
        caught_up_s = time.time() - t_up
        loss = {role: net.loss_stats(role) for role in ("a0", "learner")}
        net.set_loss("a0", 0)
        net.set_loss("learner", 0)
        alive = seen.alive("actor", "a0")
        lost_token = next((t for t, put in alive if not put and t >= t_down), None)
        back_token = next((t for t, put in alive if put and t >= t_up), None)

        # 5. clean stop once the learner is caught up with what each actor had sent a moment ago
        t_now = time.time()
        wait_for(lambda: all(st and seen.received(a) >= st[-1]["info"]["next_seq"] - 1 for a in ACTORS
                             for st in [[s for s in seen.status("actor", a) if s["t"] > t_now]]),
                 60, "the learner caught up with every actor", procs=procs)
        rcs = {a: p.stop(60, signal.SIGINT) for a, p in actors.items()}
        rcs["human"] = human.stop(60, signal.SIGINT)
        learner_status = seen.status("learner", "learner")[-1]["info"]
        rcs["learner"] = learner.stop(120, signal.SIGINT)
        rcs["monitor"] = monitor.stop(60, signal.SIGINT)
        rcs["router"] = router.stop(60, signal.SIGINT)
        logs = {p.name: p.text() for p in g.procs}
        wall = time.monotonic() - t_start

    assert all(rc == 0 for rc in rcs.values()), (rcs, {k: v[-3000:] for k, v in logs.items()})
    check = provenance_check(run_dir)
    per_actor = {a: read_json(out[a] / "summary.json") for a in ACTORS}
    resent = [ln for ln in logs["a0"].splitlines() if "re-sent batches" in ln]
    corrections = (out["a0"] / "corrections.csv").read_text().count("\n") - 1
    dup_batches = learner_status.get("duplicates", {}).get("a0", 0)
    print(f"\nnetns: {len(ROLES)} namespaces on one bridge, router {endpoint}; warm-up {t_warm - t_start:.0f} s, "
          f"wall {wall:.0f} s")
    print(f"netns: {LOSS} % loss for {LOSS_S:g} s before, during and after the outage; packets on the links "
          f"(met the loss rules / dropped): " + "; ".join(
              f"{role} in {s['in']['packets']}/{s['in']['dropped']} out {s['out']['packets']}/{s['out']['dropped']}"
              for role, s in loss.items()))
    print(f"netns: a0's link down {OUTAGE_S:g} s: a0 made {made} batches (~{made * 8} transitions) meanwhile; "
          f"its liveliness token went {'%.1f s after link down' % (lost_token - t_down) if lost_token else 'never'}, "
          f"came back {'%.2f s after link up' % (back_token - t_up) if back_token else 'never'}")
    print(f"netns: a1 (healthy link): {a1_during} batches acknowledged while a0's link was down (from 4 s after "
          f"link down to link up)")
    print(f"netns: reconnect: first new batch of a0 acknowledged {reconnect_s:.2f} s after link up; every outage "
          f"batch held {caught_up_s:.1f} s after; a0 re-sent {len(resent)} times, the learner dropped "
          f"{dup_batches} duplicate batches")
    print(f"netns: exactly once: produced {check['produced']}, stored {check['stored']}, lost {check['lost']}, "
          f"duplicated {check['duplicated']} (a0 {per_actor['a0']['transitions']}, a1 "
          f"{per_actor['a1']['transitions']} transitions; {corrections} corrections applied by a0)")
    for line in resent:
        print(f"netns: a0: {line}")
    assert check["lost"] == 0 and check["duplicated"] == 0 and not check["buffer_full"], check
    assert check["produced"] == sum(s["next_index"] for s in per_actor.values()) > 0
    assert back_token is not None and lost_token is not None, alive
    assert reconnect_s < 20, f"a0 took {reconnect_s:.1f} s after link up to get a batch through (retry period: 1 s)"
    assert corrections > 0, "the scripted human (another namespace) corrected nothing in episode 1"
