"""A third-party KhGRL human-input client: only ``zenoh`` (eclipse-zenoh) and ``msgpack``, no KhGRL imports.

It joins a run through its router, watches one actor's frames and "drags" the robot: from step ``--start`` of
episode ``--episode`` on it holds the desired position P_h a little above the KMP mean (``--dy``), one
correction per frame, for ``--steps`` frames, then releases and exits. A live hold ends with its episode: if
the episode's last frame (``last: true``) comes first, it releases there. See docs/protocol.md ("Write your own
client").

    python deploy/examples/drag_client.py --connect tcp/127.0.0.1:7447 --run RUN --actor a0 --steps 40
"""

import argparse
import json
import math
import queue
import sys
import time

import msgpack
import zenoh


def envelope(kind, sender, seq, **fields):
    msg = {"v": 1, "kind": kind, "sender": sender, "seq": seq, "ts": time.time()}
    msg.update(fields)
    return msgpack.packb(msg, use_bin_type=True)


def parse_frame(payload):
    """The fields this client uses, or None for anything that is not a sound frame (never trust the wire)."""
    try:
        m = msgpack.unpackb(payload, raw=False)
    except Exception:  # noqa: BLE001 - garbage
        return None
    if not isinstance(m, dict) or m.get("v") != 1 or m.get("kind") != "frame":
        return None
    try:
        ep, t, mean = m["episode"], m["t"], m["mean"]
        ok = isinstance(ep, int) and isinstance(t, int) and 1 <= len(mean) <= 64 and all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in mean)
    except (KeyError, TypeError):
        return None
    return {"episode": ep, "t": t, "mean": [float(v) for v in mean], "last": m.get("last") is True} if ok else None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", help="router endpoint")
    p.add_argument("--run", required=True, help="run id (printed by khgrl up, in RUN_DIR/config.json)")
    p.add_argument("--actor", default="a0")
    p.add_argument("--client", default="drag", help="client id (key chunk: no / * $ ? # or space)")
    p.add_argument("--episode", type=int, default=1, help="episode (1-based) in which to drag")
    p.add_argument("--start", type=int, default=20, help="first step t of that episode to react to")
    p.add_argument("--steps", type=int, default=40, help="frames to hold P_h for")
    p.add_argument("--dy", type=float, default=0.05, help="P_h = KMP mean + dy along --axis (default: %(default)s)")
    p.add_argument("--axis", type=int, default=1, help="the output --dy moves (default: %(default)s, the task's y)")
    p.add_argument("--wait", type=float, default=120.0, help="give up after this many seconds without the drag")
    args = p.parse_args(argv)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    root = f"khgrl/{args.run}"
    frames = queue.Queue(maxsize=1024)

    def on_frame(sample):  # zenoh callback: only enqueue (never call zenoh or block here)
        try:
            frames.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            pass

    sent, seq = 0, 0
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"{root}/actor/{args.actor}/frame", on_frame)
        pub = session.declare_publisher(f"{root}/human/{args.client}/correction", express=True,
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        priority=zenoh.Priority.INTERACTIVE_HIGH)
        token = session.liveliness().declare_token(f"{root}/alive/human/{args.client}")
        deadline = time.monotonic() + args.wait
        try:
            while sent < args.steps and time.monotonic() < deadline:
                try:
                    f = parse_frame(frames.get(timeout=0.1))
                except queue.Empty:
                    f = None
                if f is None:  # (a client that must survive a paused actor re-sends its P_h every 100 ms here)
                    continue
                if sent == 0 and (f["episode"] != args.episode or f["t"] < args.start):
                    continue
                if f["last"]:  # the episode ended, and a live hold ends with it (the actor ends it too)
                    break
                p_h = [v + (args.dy if k == args.axis else 0.0) for k, v in enumerate(f["mean"])]
                pub.put(envelope("correction", args.client, seq, client=args.client, actor=args.actor, active=True,
                                 p_h=p_h, episode=f["episode"], t=f["t"]))
                seq += 1
                sent += 1
        finally:
            if sent:  # let go
                pub.put(envelope("correction", args.client, seq, client=args.client, actor=args.actor, active=False))
            token.undeclare()
            pub.undeclare()
            sub.undeclare()
    print(f"drag_client: held P_h for {sent} frames of actor {args.actor}", flush=True)
    return 0 if sent == args.steps else 1


if __name__ == "__main__":
    sys.exit(main())
