"""``khgrl up``: start a Zenoh router, the learner, one or more actors and the human-input process as
separate OS processes (spawned with ``subprocess``, never forked from a process with an open session),
show one live progress view, and stop everything cleanly when the actors finish, on Ctrl-C, or when a
process dies (reported with its exit code and the tail of its log; the run then fails).

Run directory layout::

    RUN_DIR/config.json          the launch configuration
    RUN_DIR/logs/<process>.log   each process's stdout/stderr
    RUN_DIR/learner/...          checkpoints, TensorBoard scalars
    RUN_DIR/actor-<id>/...       episodes.csv/json, summary.json, corrections.csv (applied human
                                 corrections, replayable), tb/ (per-episode TensorBoard scalars)
    RUN_DIR/summary.json         exit codes, wall time, per-actor results
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import secrets
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from common.protocol import Keys, ProtocolError, RejectCounter, decode, encode
from common.session import StopFlag, free_port, install_stop_handlers, open_client

__all__ = ["main", "build_parser"]


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    essential: bool = True  # the run fails if it exits non-zero
    returncode: int | None = None
    log_fh: object = field(default=None, repr=False)

    def start(self, env: dict) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log_fh = open(self.log_path, "ab")
        self.proc = subprocess.Popen(self.argv, stdout=self.log_fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)

    def poll(self) -> int | None:
        if self.proc is not None and self.returncode is None:
            self.returncode = self.proc.poll()
        return self.returncode

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.poll() is None:
            try:
                os.kill(self.proc.pid, sig)
            except ProcessLookupError:
                pass

    def wait(self, timeout: float) -> int | None:
        if self.proc is None:
            return None
        try:
            self.returncode = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pass
        return self.returncode

    def tail(self, n: int = 15) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def close(self) -> None:
        if self.log_fh is not None:
            self.log_fh.close()


def _module_argv(module: str, args: list[str]) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", module, *args]


def _wait_listening(host: str, port: int, timeout: float, child: Child) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if child.poll() is not None:
            raise RuntimeError(f"router exited with code {child.returncode}:\n{child.tail()}")
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return
        time.sleep(0.05)
    raise RuntimeError(f"router did not listen on {host}:{port} within {timeout} s")


def _make_run_id(run_dir: Path) -> str:
    stem = "".join(c if c.isalnum() or c in "-_" else "-" for c in run_dir.name)[:40] or "run"
    return f"{stem}-{secrets.token_hex(3)}"


def _num(value, default: float = 0.0) -> float:
    """A finite number from a (validated, but free-form in places) message field, else ``default``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return default
    value = float(value)
    return value if value == value and abs(value) != float("inf") else default


class ProgressView:
    """Live table of episodes, success, return, interventions (count, human steps, fraction of clipped human actions,
    mean |xi_h|), learner updates and weight version."""

    def __init__(self, actors: list[str], episodes: int, enabled: bool) -> None:
        self.actors = {a: self._row() for a in actors}
        self.episodes = episodes
        self.learner: dict = {}
        self.enabled = enabled
        self._live = None

    @staticmethod
    def _row() -> dict:
        return {"done": 0, "success": 0, "last_return": None, "interventions": 0, "count": 0, "clipped": 0,
                "xi_sum": 0.0}

    def __enter__(self):
        if self.enabled:
            from rich.live import Live

            self._live = Live(self._table(), refresh_per_second=4, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc):
        if self._live is not None:
            self._live.update(self._table())
            self._live.__exit__(*exc)

    def episode(self, msg: dict) -> None:
        st = msg["stats"]
        row = self.actors.setdefault(msg["actor"], self._row())
        steps = int(_num(st.get("intervention_steps")))
        clipped = int(_num(st.get("clipped_steps")))
        count = int(_num(st.get("interventions")))
        xi = _num(st.get("mean_abs_xi_h"))
        row["done"] = max(row["done"], int(_num(st.get("episode"))))
        row["success"] += int(st.get("success") is True)
        row["last_return"] = _num(st.get("ret"))
        row["interventions"] += steps
        row["count"] += count
        row["clipped"] += clipped
        row["xi_sum"] += xi * steps
        if not self.enabled:
            frac = f"{clipped / steps:.0%}" if steps else "-"
            print(f"[{msg['actor']}] episode {st.get('episode')}: return {_num(st.get('ret')):.1f} "
                  f"success={st.get('success')} interventions={steps} "
                  f"(count {count}, clipped {frac}, mean |xi_h| {xi:.3g})", flush=True)
        self.refresh()

    def status(self, msg: dict) -> None:
        if msg.get("role") == "learner":
            # status info is free-form: keep only the numbers the view shows
            info = msg["info"]
            self.learner = {k: info[k] for k in ("ingested", "gradient_steps", "grad_steps_per_s", "version")
                            if isinstance(info.get(k), (int, float)) and not isinstance(info.get(k), bool)}
            self.refresh()

    def refresh(self) -> None:
        if self._live is not None:
            self._live.update(self._table())

    def _table(self):
        from rich.table import Table

        t = Table(title="KhGRL run")
        for col in ("actor", "episodes", "successes", "last return", "interventions", "human steps", "clipped",
                    "mean |xi_h|"):
            t.add_column(col, justify="right")
        for a, r in self.actors.items():
            ret = "-" if r["last_return"] is None else f"{r['last_return']:.1f}"
            n = r["interventions"]
            clipped = f"{r['clipped']} ({r['clipped'] / n:.0%})" if n else str(r["clipped"])
            xi = f"{r['xi_sum'] / n:.3g}" if n else "-"
            t.add_row(a, f"{r['done']}/{self.episodes}", str(r["success"]), ret, str(r["count"]), str(n), clipped, xi)
        li = self.learner
        t.caption = (f"learner: {li.get('ingested', 0)} transitions, {li.get('gradient_steps', 0)} gradient steps "
                     f"({li.get('grad_steps_per_s', 0):.0f}/s), weights v{li.get('version', 0)}") if li else "learner: waiting"
        return t


def run(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    run_id = args.run or _make_run_id(run_dir)
    keys = Keys(run_id)
    actors = [f"a{i}" for i in range(args.actors)]
    if args.connect:
        endpoint = args.connect
    else:
        port = args.port or free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
    config = {k: v for k, v in vars(args).items() if k != "func"}
    config.update(run=run_id, endpoint=endpoint, actors_ids=actors, argv=sys.argv, started=time.strftime("%Y-%m-%dT%H:%M:%S"))
    (run_dir / "config.json").write_text(json.dumps(config, indent=2, default=str))

    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    logs = run_dir / "logs"
    common = ["--run", run_id, "--connect", endpoint]
    children: list[Child] = []
    router = None
    if not args.connect:
        router = Child("router", _module_argv("router", ["--listen", endpoint]), logs / "router.log")
        children.append(router)
    learner_args = [*common, "--run-dir", str(run_dir), "--seed", str(args.seed), "--learning-starts", str(args.learning_starts),
                    "--nice", str(args.learner_nice)]
    if args.resume:
        learner_args.append("--resume")
    children.append(Child("learner", _module_argv("learner", learner_args), logs / "learner.log"))
    for i, aid in enumerate(actors):
        children.append(Child(aid, _module_argv("actor", [
            *common, "--run-dir", str(run_dir), "--id", aid, "--scenario", args.scenario, "--method", args.method,
            "--episodes", str(args.episodes), "--seed", str(args.seed + i), "--max-lead", str(args.max_lead),
            "--rate", str(args.rate), "--learning-starts", str(args.learning_starts),
            *(["--rt-priority", str(args.actor_rt_priority)] if args.actor_rt_priority else []),
        ]), logs / f"{aid}.log"))
    if args.method == "khgrl" and args.human != "none":
        hargs = [args.human, *common, "--scenario", args.scenario, "--actor", "*", "--seed", str(args.seed)]
        if args.human_episodes:
            hargs += ["--episodes", *map(str, args.human_episodes)]
        children.append(Child(f"human-{args.human}", _module_argv("human", hargs), logs / f"human-{args.human}.log"))

    flag = StopFlag()
    install_stop_handlers(flag)
    t0 = time.time()
    failed: list[str] = []
    inbox: queue.Queue = queue.Queue()
    rejects = RejectCounter("launcher")
    try:
        if router is not None:
            router.start(env)
            host, port = endpoint.split("/")[1].rsplit(":", 1)
            _wait_listening(host, int(port), 15.0, router)
        for ch in children:
            if ch is not router:
                ch.start(env)
        print(f"khgrl up: run {run_id} on {endpoint}; logs in {logs}", flush=True)
        with open_client(endpoint) as session, ProgressView(actors, args.episodes, not args.no_progress) as view:
            subs = [
                session.declare_subscriber(keys.episode("*"), lambda s: inbox.put(("episode", s.payload.to_bytes()))),
                session.declare_subscriber(keys.status("learner", "*"), lambda s: inbox.put(("status", s.payload.to_bytes()))),
            ]
            try:
                deadline = t0 + args.timeout if args.timeout > 0 else None
                while not flag:
                    try:
                        kind, payload = inbox.get(timeout=0.25)
                        msg = decode(kind, payload)
                        view.episode(msg) if kind == "episode" else view.status(msg)
                    except queue.Empty:
                        pass
                    except ProtocolError as exc:
                        rejects.reject(kind, kind, exc)
                    for ch in children:
                        rc = ch.poll()
                        if rc not in (None, 0) and ch.name not in failed:
                            failed.append(ch.name)
                    if failed:
                        break
                    if all(ch.poll() == 0 for ch in children if ch.name in actors):
                        break
                    if deadline is not None and time.time() > deadline:
                        print(f"khgrl up: timeout after {args.timeout} s", flush=True)
                        failed.append("timeout")
                        break
                # ask everyone left to stop (the learner checkpoints first); after a failure a process may not
                # have subscribed yet, so wait less before falling back to signals
                session.put(keys.control("all"), encode("control", "launcher", 0, command="stop"))
                grace = args.stop_timeout if not failed else min(args.stop_timeout, 5.0)
                stop_deadline = time.time() + grace
                while time.time() < stop_deadline and any(ch.poll() is None for ch in children if ch is not router):
                    time.sleep(0.1)
            finally:
                for s in subs:
                    s.undeclare()
    finally:
        # signal everything still running at once, then wait jointly: SIGINT (clean stop), SIGKILL after 10 s
        for sig, grace in ((signal.SIGINT, 10.0), (signal.SIGKILL, 5.0)):
            alive = [ch for ch in children if ch.poll() is None]
            for ch in alive:
                ch.signal(sig)
            deadline = time.time() + grace
            while alive and time.time() < deadline:
                time.sleep(0.05)
                alive = [ch for ch in alive if ch.poll() is None]
        for ch in children:
            ch.close()
    wall = time.time() - t0
    codes = {ch.name: ch.returncode for ch in children}
    for name in failed:
        if name == "timeout":
            continue
        ch = next(c for c in children if c.name == name)
        print(f"khgrl up: process {name} exited with code {ch.returncode}; last lines of {ch.log_path}:\n{ch.tail()}", file=sys.stderr)
    summary = {"run": run_id, "wall_time_s": wall, "exit_codes": codes, "failed": failed, "interrupted": bool(flag),
               "launcher_rejects": rejects.by_kind()}
    for aid in actors:
        p = run_dir / f"actor-{aid}" / "summary.json"
        if p.exists():
            summary[aid] = json.loads(p.read_text())
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(f"khgrl up: finished in {wall:.0f} s; exit codes {codes}; results in {run_dir}", flush=True)
    if flag:
        return 130
    return 1 if failed else 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl up", description="Launch router, learner, actor(s) and human-input process locally.")
    p.add_argument("--scenario", default="high_cov", choices=["high_cov", "low_cov"])
    p.add_argument("--method", default="khgrl", choices=["khgrl", "kgrl"])
    p.add_argument("--episodes", type=int, default=60, help="episodes per actor")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run-dir", default="runs/demo")
    p.add_argument("--run", default=None, help="run id (key prefix khgrl/<run>/); default: derived from the run dir")
    p.add_argument("--actors", type=int, default=1)
    p.add_argument("--human", default="scripted", choices=["scripted", "gui", "none"],
                   help="human-input client (khgrl only): scripted, gui (a pygame window to drag the robot), none")
    p.add_argument("--human-episodes", type=int, nargs="+", default=None, help="episodes with corrections (default: the paper's)")
    p.add_argument("--connect", default=None, help="join the router at tcp/HOST:PORT instead of starting one")
    p.add_argument("--port", type=int, default=0, help="router port on 127.0.0.1 (default: a free one)")
    p.add_argument("--max-lead", type=int, default=8, help="transitions an actor may run ahead of the learner's training")
    p.add_argument("--rate", type=float, default=0.0, help="actor control rate in Hz (0: as fast as allowed)")
    p.add_argument("--learning-starts", type=int, default=100)
    p.add_argument("--actor-rt-priority", type=int, default=0,
                   help="actors' control loops under SCHED_FIFO at this priority (needs --rate and root; default off)")
    p.add_argument("--learner-nice", type=int, default=5,
                   help="run the learner at this nice level so training yields the CPU to actor control loops (default %(default)s)")
    p.add_argument("--resume", action="store_true", help="resume the learner from RUN_DIR/learner/checkpoint")
    p.add_argument("--timeout", type=float, default=0.0, help="fail the run after this many seconds (0: none)")
    p.add_argument("--stop-timeout", type=float, default=60.0, help="seconds to wait for processes to stop")
    p.add_argument("--no-progress", action="store_true", help="print episode lines instead of the live table")
    p.set_defaults(func=run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.actors < 1 or args.episodes < 1:
        print("khgrl up: --actors and --episodes must be >= 1", file=sys.stderr)
        return 2
    return run(args)
