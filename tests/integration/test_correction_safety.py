"""Safety of the correction path, against a real actor process over a real router.

This test process plays several human-input clients (one Zenoh session, one publisher per client id):

* alice drags; bob sends corrections while alice holds the robot: ignored and counted, never applied;
* carol drags and then goes silent without releasing: her P_h drives the robot for ``human_silence_s``, then the
  watchdog holds the robot still (no step) until the correction timeout ends her intervention;
* dave drags to a point just outside the workspace (within 10 % of its extent): projected onto it, applied, counted
  (farther out is refused: tests/unit/test_human_limits.py, tests/integration/test_attack_humans.py);
* eve sends non-finite P_h and garbage, mallory corrects an actor that does not exist: rejected or ignored,
  counted and logged -- and the run goes on to the end;
* frank holds the robot until the episode's last frame and says nothing more: his hold ends with that
  episode (it never drives the next one, however recent his last message).

The actor runs without a learner (its final flush times out: exit code 3) at 50 Hz.
"""

from __future__ import annotations

import csv
import queue
import time

import msgpack
import numpy as np
import pytest

from helpers import ProcGroup, read_json, unique_run

TIMEOUT_S = 0.5
SILENCE_S = 0.3  # the actor's human_silence_s (its default)


class Clients:
    """This test's human-input clients: one Zenoh session, one publisher per client id, reacting to the frames.

    :param session: the test's Zenoh session.
    :param keys: the run's keys.
    """

    def __init__(self, session, keys) -> None:
        from khgrl.human_bridge.client import CorrectionPublisher

        self.session, self.keys = session, keys
        self.frames: queue.Queue = queue.Queue()
        self.sub = session.declare_subscriber(keys.frame("a0"), lambda smp: self.frames.put(smp.payload.to_bytes()))
        self.pubs = {c: CorrectionPublisher(session, keys, c)
                     for c in ("alice", "bob", "carol", "dave", "mallory", "frank")}

    def next_frame(self, timeout: float = 30.0):
        from khgrl.common.wire.messages import Frame
        from khgrl.common.wire.protocol import decode

        return decode(Frame, self.frames.get(timeout=timeout))

    def drain(self) -> None:
        while True:
            try:
                self.frames.get_nowait()
            except queue.Empty:
                return

    def alice_and_bob(self) -> int:
        """alice holds for 20 frames; bob tries to take over during the last 15. Returns bob's messages."""
        bob_sent = 0
        for k in range(20):
            f = self.next_frame()
            self.pubs["alice"].send("a0", np.array(f.mean) + [0.0, 0.04], f.episode, f.t)
            if k >= 5:
                self.pubs["bob"].send("a0", np.array(f.mean) - [0.0, 0.1], f.episode, f.t)
                bob_sent += 1
        self.pubs["bob"].send("a0", None)  # bob's release while alice holds: not his to give
        bob_sent += 1
        time.sleep(0.05)
        self.pubs["alice"].send("a0", None)
        for _ in range(5):
            self.next_frame()
        return bob_sent

    def carol(self) -> float:
        """carol: 5 frames, then silence. Returns the time of her last message."""
        for _ in range(5):
            f = self.next_frame()
            self.pubs["carol"].send("a0", np.array(f.mean) + [0.0, 0.03], f.episode, f.t)
        carol_last = time.time()
        time.sleep(TIMEOUT_S + 0.5)
        self.drain()
        return carol_last

    def dave(self) -> None:
        """dave: a P_h outside the workspace."""
        for _ in range(6):
            f = self.next_frame()
            self.pubs["dave"].send("a0", np.array([1.05, -0.05]), f.episode, f.t)
        self.pubs["dave"].send("a0", None)

    def mallory_and_eve(self) -> int:
        """mallory corrects an actor that does not exist; eve sends non-finite P_h and garbage. Returns how
        many of eve's messages were sent."""
        import zenoh

        for _ in range(3):
            self.pubs["mallory"].send("a9", np.array([0.5, 0.5]), 1, 0)
        evil = self.keys.correction("eve")
        base = {"v": 1, "kind": "correction", "sender": "eve", "seq": 0, "ts": time.time(), "client": "eve",
                "actor": "a0", "active": True}
        bad = [msgpack.packb(dict(base, p_h=[float("nan"), 0.5])),
               msgpack.packb(dict(base, p_h=[0.5, float("inf")])),
               msgpack.packb(dict(base, p_h=[0.5, float("-inf")])),
               b"\xc1\xc1 garbage \x00",
               msgpack.packb([1, 2, 3]),
               msgpack.packb(dict(base, p_h="up")),
               msgpack.packb(dict(base, v=7, p_h=[0.5, 0.5]))]
        for payload in bad:
            self.session.put(evil, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        return len(bad)

    def frank(self) -> int:
        """frank holds on every frame up to the episode's last one, then says nothing. Returns that episode."""
        f = self.next_frame()
        if f.last:
            f = self.next_frame()
        episode = f.episode
        assert episode < 3, "the earlier clients took longer than expected: no next episode"
        while not f.last:
            self.pubs["frank"].send("a0", np.array(f.mean) + [0.0, 0.02], f.episode, f.t)
            f = self.next_frame()
        for _ in range(int(2 * TIMEOUT_S * 50)):  # the next episode runs on, longer than the timeout
            self.next_frame()
        return episode

    def close(self) -> None:
        self.sub.undeclare()
        for p in self.pubs.values():
            p.close()


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_arbitration_timeout_projection_and_rejects_with_a_real_actor(tmp_path):
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys

    run, run_dir = unique_run("safe"), tmp_path / "run"
    keys = Keys(run)
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        actor = g.actor(run, ep, "--scenario", "low_cov", "--method", "khgrl", "--episodes", "3", "--rate", "50",
                        "--learning-starts", "100000", "--flush-timeout", "0.5", "--learner-wait", "0",
                        "--correction-timeout", str(TIMEOUT_S), run_dir=run_dir)
        with open_client(ep) as s:
            clients = Clients(s, keys)
            try:
                f = clients.next_frame(120)  # the actor is up and stepping
                while f.t < 5:
                    f = clients.next_frame()
                bob_sent = clients.alice_and_bob()
                carol_last = clients.carol()
                clients.dave()
                bad = clients.mallory_and_eve()
                for _ in range(10):  # the run goes on: frames keep coming (next_frame fails after 30 s without one)
                    clients.next_frame()
                frank_episode = clients.frank()
            finally:
                clients.close()
        assert actor.wait(150) == 3, actor.tail()  # no learner: only the final flush times out

    check_results(run_dir, bob_sent, carol_last, bad, frank_episode)


def check_results(run_dir, bob_sent: int, carol_last: float, bad: int, frank_episode: int) -> None:
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    c = summary["corrections"]
    assert summary["episodes"] == 3 and summary["stopped_by"] is None
    assert c["holds"] == 4, c  # alice, carol, dave, frank
    assert c["releases"] == 3 and c["timeouts"] == 1, c  # alice and dave let go; carol timed out
    assert c["episode_end_releases"] == 1, c  # frank's hold ended with its episode
    assert c["ignored_other_client"] == bob_sent, c
    assert c["ignored_other_actor"] == 3, c
    assert summary["rejects"] == {"correction": bad}, summary["rejects"]
    log = (run_dir / "actor-a0" / "actor.log").read_text()
    assert log.count("rejected correction message") >= 5  # each distinct reason is logged
    assert "p_h[0]: not finite" in log and "p_h[1]: not finite" in log and "not msgpack" in log
    assert "correction client carol silent" in log

    with open(run_dir / "actor-a0" / "corrections.csv", newline="") as fh:
        rec = list(csv.DictReader(fh))
    clients = [r["client"] for r in rec]
    # applied in order: alice's hold, carol's, dave's, frank's; never bob's
    order = [c for i, c in enumerate(clients) if i == 0 or clients[i - 1] != c]
    assert order == ["alice", "carol", "dave", "frank"], order
    frank = [r for r in rec if r["client"] == "frank"]
    assert frank and {int(r["episode"]) for r in frank} == {frank_episode}, "a live hold outlived its episode"
    alice = [r for r in rec if r["client"] == "alice"]
    assert 18 <= len(alice) <= 22
    # carol's stale P_h drove the robot for about human_silence_s after her last message, not more; then the robot
    # was held (no step) until the timeout released her
    carol = [r for r in rec if r["client"] == "carol"]
    held = float(carol[-1]["time"]) - carol_last
    assert SILENCE_S - 0.15 <= held <= SILENCE_S + 0.15, held
    assert len(carol) >= 5 + int(0.6 * SILENCE_S * 50)
    safety = summary["safety"]
    assert safety["human_silence_holds"] == 1 and 0.1 <= safety["held_s"]["human"] <= TIMEOUT_S - SILENCE_S + 0.1
    # dave's out-of-workspace P_h was applied, projected, and counted
    dave = [r for r in rec if r["client"] == "dave"]
    assert 5 <= len(dave) <= 8 and all(r["projected"] == "1" for r in dave)
    assert all((float(r["p_h_x"]), float(r["p_h_y"])) == (1.05, -0.05) for r in dave)
    assert not any(r["projected"] == "1" for r in rec if r["client"] != "dave")
    assert c["projected_steps"] == len(dave)
    with open(run_dir / "actor-a0" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sum(int(r["projected_steps"]) for r in rows) == len(dave)
    assert sum(int(r["intervention_steps"]) for r in rows) == len(rec)
