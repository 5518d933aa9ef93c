"""``khgrl human``: the human-input process. It hosts one human-input client and talks to actors only
through Zenoh messages (docs/protocol.md): it reads the actor's frames and publishes corrections.

Clients:

* ``scripted`` -- the reproducible stand-in for a person (:mod:`human_bridge.scripted`): in the given
  episodes, over the scenario's help window, it holds the desired position on a safe path through the gaps.
* ``gui`` -- a pygame window: a person drags the robot with the mouse (:mod:`human_bridge.gui`).
* ``replay`` -- feeds a recorded ``corrections.csv`` into a new run at the same episodes and steps
  (:mod:`human_bridge.replay`).

A correction stream is: ``active=True`` messages with ``p_h`` while the person drags (sent for every
frame, so the actor can tell a live drag from a dead client), then one ``active=False`` on release.
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
from pathlib import Path

from common.protocol import Keys, ProtocolError, RejectCounter, decode, encode
from common.session import DEFAULT_ENDPOINT, StopFlag, install_stop_handlers, open_client
from human_bridge.scripted import PAPER_EPISODES, ScriptedHuman, ScriptedHumanConfig

__all__ = ["main", "CorrectionPublisher"]

log = logging.getLogger("khgrl.human")


class CorrectionPublisher:
    """Publishes one client's correction stream (sequence-numbered, express, high priority)."""

    def __init__(self, session, keys: Keys, client: str) -> None:
        import zenoh

        self.client = client
        self.seq = 0
        self.sent = 0
        self._pub = session.declare_publisher(
            keys.correction(client),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
            express=True,
        )
        self.active: dict[str, bool] = {}

    def send(self, actor: str, p_h, episode: int = 0, t: int = 0, step: int | None = None) -> None:
        """``p_h`` (2,) to drag, or None to release. With ``step`` the message is step-addressed: P_h (or the
        release) is for that step of ``episode``, and it is sent even when there is nothing to release -- the
        actor waits for this client's word on every step of the episode (docs/protocol.md)."""
        active = p_h is not None
        if not active and step is None and not self.active.get(actor, False):
            return  # nothing to release
        fields = {"client": self.client, "actor": actor, "active": active, "episode": int(episode), "t": int(t)}
        if step is not None:
            fields["step"] = int(step)
        if active:
            fields["p_h"] = [float(p_h[0]), float(p_h[1])]
        self._pub.put(encode("correction", self.client, self.seq, **fields))
        self.seq += 1
        self.sent += 1
        self.active[actor] = active

    def close(self) -> None:
        self._pub.undeclare()


def _run_scripted(args: argparse.Namespace) -> int:
    import zenoh

    keys = Keys(args.run)
    human = ScriptedHuman(args.scenario, ScriptedHumanConfig(episodes=tuple(args.episodes), noise=args.noise, seed=args.seed))
    flag = StopFlag()
    install_stop_handlers(flag)
    rejects = RejectCounter(f"human/{args.id}")
    frames: queue.Queue = queue.Queue(maxsize=1024)
    with open_client(args.connect) as session:
        token = session.liveliness().declare_token(keys.alive("human", args.id))
        frame_sub = session.declare_subscriber(keys.frame(args.actor), lambda s: _offer(frames, s))
        control_sub = session.declare_subscriber(keys.control("human"), lambda s: _control(s, flag, rejects))
        control_all = session.declare_subscriber(keys.control("all"), lambda s: _control(s, flag, rejects))
        pub = CorrectionPublisher(session, keys, args.id)
        status_pub = session.declare_publisher(keys.status("human", args.id), congestion_control=zenoh.CongestionControl.DROP)
        print(f"khgrl human scripted ({args.id}) driving actor {args.actor} in episodes {list(args.episodes)}", flush=True)
        n_frames = 0
        means: dict = {}  # step -> KMP mean, from the frames seen
        announced: set = set()  # (actor, episode) whose lock-step was announced
        try:
            while not flag:
                try:
                    key, payload = frames.get(timeout=0.2)
                except queue.Empty:
                    continue
                try:
                    frame = decode("frame", payload)
                except ProtocolError as exc:
                    rejects.reject("frame", key, exc)
                    continue
                n_frames += 1
                # The frame describes step t. In a help episode, answer with a step-addressed correction for
                # step t + 1 (P_h from the mean there): the actor waits for it, so latency does not shift
                # P_h against the mean (docs/distributed_runs.md). Other episodes: say nothing.
                ep, t, actor = frame["episode"], frame["t"], frame["actor"]
                means.setdefault(t, frame["mean"])  # the KMP mean is the same in every episode
                if human.active_in(ep) and "next_mean" in frame:
                    pub.send(actor, human.correction(ep, frame["next_mean"]), ep, t, step=t + 1)
                elif pub.active.get(actor, False):
                    pub.send(actor, None, ep, t)
                if human.active_in(ep + 1) and (actor, ep + 1) not in announced:
                    # announce lock-step for the next episode with the word for its step 0
                    announced.add((actor, ep + 1))
                    p0 = human.correction(ep + 1, means[0]) if 0 in means else None
                    pub.send(actor, p0, ep + 1, t, step=0)
                if n_frames % 50 == 0:
                    status_pub.put(encode("status", args.id, n_frames // 50, role="human",
                                          info={"frames": n_frames, "corrections": pub.sent, "rejects": rejects.by_kind()}))
        finally:
            for actor, active in list(pub.active.items()):
                if active:
                    pub.send(actor, None)
            pub.close()
            frame_sub.undeclare()
            control_sub.undeclare()
            control_all.undeclare()
            status_pub.undeclare()
            token.undeclare()
    print(f"khgrl human: {n_frames} frames seen, {pub.sent} correction messages sent, {rejects.total} rejected", flush=True)
    return 0


def _offer(q: queue.Queue, sample) -> None:
    """Zenoh callback: hand the bytes over, never block (drop the oldest frame when full)."""
    item = (str(sample.key_expr), sample.payload.to_bytes())
    try:
        q.put_nowait(item)
    except queue.Full:
        try:
            q.get_nowait()
        except queue.Empty:
            pass
        q.put_nowait(item)


def _control(sample, flag: StopFlag, rejects: RejectCounter) -> None:
    try:
        msg = decode("control", sample.payload.to_bytes())
    except ProtocolError as exc:
        rejects.reject("control", str(sample.key_expr), exc)
        return
    if msg["command"] == "stop":
        flag.set("stop command")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khgrl human", description="Human-input process: hosts one human-input client.")
    sub = parser.add_subparsers(dest="client", required=True, metavar="CLIENT")
    p = sub.add_parser("scripted", help="the scripted human: reproducible corrections along a safe path")
    p.add_argument("--run", required=True, help="run id (key prefix khgrl/<run>/)")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, help="router endpoint (default %(default)s)")
    p.add_argument("--scenario", default="high_cov", choices=["high_cov", "low_cov"])
    p.add_argument("--actor", default="a0", help="actor id to drive")
    p.add_argument("--episodes", type=int, nargs="+", default=list(PAPER_EPISODES), help="1-based episodes with corrections")
    p.add_argument("--noise", type=float, default=0.0, help="std of hand noise on P_h (workspace units)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--id", default="scripted", help="client id")
    p.add_argument("--run-dir", default=None, help="(unused by the scripted client; accepted for the launcher)")
    p.set_defaults(func=_run_scripted)
    from human_bridge.gui import add_parser as add_gui

    add_gui(sub, DEFAULT_ENDPOINT)
    from human_bridge.replay import add_parser as add_replay

    add_replay(sub, DEFAULT_ENDPOINT)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    args = build_parser().parse_args(argv)
    if args.run_dir:
        Path(args.run_dir).mkdir(parents=True, exist_ok=True)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
