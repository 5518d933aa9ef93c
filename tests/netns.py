"""Linux network namespaces for multi-host tests: one namespace per "host", joined by veth links to a bridge
in a dedicated switch namespace, so that processes talk over a real (virtual) network with its own addresses,
packet loss and link failures -- and nothing touches the host's own network.

    reason = netns_available()          # None, or why namespaces cannot be used here (skip with it)
    with Network(["router", "learner", "actor"]) as net:
        net.addr("router")              # "10.X.Y.1": the hosts are .1, .2, ... of one private /24
        proc = net.run_in("actor", [sys.executable, "-c", "..."])   # a Popen inside the actor's namespace
        net.set_loss("actor", 5)        # nftables: drop 5 % of the packets in and out of its link, at random
        net.link_down("actor"); net.link_up("actor")              # ``ip link set <veth> down/up``
        net.loss_stats("actor")         # packets seen and dropped by the loss rules, per direction

Layout: namespace ``khgrl-<pid>-<n>-sw`` holds bridge ``br0``; each host namespace ``khgrl-<pid>-<n>-<role>``
holds ``lo`` (up) and ``eth0`` (its address, /24), the other end of which is ``v<i>`` on the bridge. Links are
created directly inside the namespaces, so no interface ever appears in the root namespace. The /24 is derived
from the test process's PID (10.128-191.X.0); the namespaces are isolated, so a clash could not matter anyway.

Loss uses nftables, since the kernels these tests run on have no ``netem`` qdisc: a table ``inet khgrl_loss``
in the host's namespace with an input and an output chain, each with a counting rule and a ``numgen random
mod 100 < N drop`` rule, for packets on ``eth0`` from/to the test's subnet only (never loopback).

Cleanup always runs (``with``, :meth:`Network.destroy`, and an ``atexit`` hook as a last resort): every process
in the namespaces is killed by PID (``ip netns pids``), then the namespaces are deleted. Namespaces that an
earlier test process left behind (its PID gone) are deleted on the next start if no process is in them.
"""

from __future__ import annotations

import atexit
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass
from typing import Sequence

from helpers import pid_alive

__all__ = ["Host", "Network", "netns_available", "remove_stale", "LOSS_TABLE"]

LOSS_TABLE = "khgrl_loss"
PREFIX = "khgrl-"
DEV = "eth0"
_counter = itertools.count()
_available: list[str | None] = []  # cached result of netns_available()


def _ip(*args: str, check: bool = True, timeout: float = 20.0) -> subprocess.CompletedProcess:
    """Run ``ip ARGS``; :class:`RuntimeError` with its stderr when ``check`` and it fails."""
    return _run(["ip", *args], check=check, timeout=timeout)


def _run(argv: list[str], check: bool = True, timeout: float = 20.0, stdin: str | None = None):
    out = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, input=stdin)
    if check and out.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({out.returncode}): {out.stderr.strip()}")
    return out


def netns_available() -> str | None:
    """None when this process can make network namespaces with veth links and nftables rules; otherwise the
    reason (not root, ``ip`` or ``nft`` missing, namespaces or nftables not permitted), for ``pytest.skip``."""
    if not _available:
        _available.append(_probe())
    return _available[0]


def _probe() -> str | None:
    if os.name != "posix" or not os.path.isdir("/proc/self/ns"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return f"network namespaces need root (running as uid {os.geteuid()})"
    for tool, package in (("ip", "iproute2"), ("nft", "nftables")):
        if shutil.which(tool) is None:
            return f"`{tool}` not found (install {package})"
    ns = f"{PREFIX}{os.getpid()}-probe"
    try:
        _ip("netns", "add", ns)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot create a network namespace: {exc}"
    try:
        _ip("-n", ns, "link", "add", "p0", "type", "veth", "peer", "name", "p1")
        _run(["ip", "netns", "exec", ns, "nft", "add", "table", "inet", LOSS_TABLE])
        _run(["ip", "netns", "exec", ns, "nft", "add", "chain", "inet", LOSS_TABLE, "c",
              "{ type filter hook input priority 0; policy accept; }"])
        _run(["ip", "netns", "exec", ns, "nft", "add", "rule", "inet", LOSS_TABLE, "c",
              "numgen", "random", "mod", "100", "<", "1", "counter"])
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return f"network namespaces are not usable here: {exc}"
    finally:
        _ip("netns", "del", ns, check=False)
    return None


def _ns_pids(ns: str) -> list[int]:
    out = _ip("netns", "pids", ns, check=False)
    return [int(p) for p in out.stdout.split() if p.isdigit()]


def _kill_ns_processes(ns: str, timeout: float = 10.0) -> list[int]:
    """SIGKILL every process in namespace ``ns``, one PID at a time, and wait until none is left; returns the
    PIDs killed."""
    killed: list[int] = []
    deadline = time.monotonic() + timeout
    while True:
        pids = [p for p in _ns_pids(ns) if p != os.getpid()]
        if not pids or time.monotonic() > deadline:
            return killed
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            except ProcessLookupError:
                pass
        time.sleep(0.05)


def remove_stale() -> list[str]:
    """Delete namespaces ``khgrl-<pid>-...`` whose creating process is gone and that hold no process (an earlier
    test run killed before its cleanup); returns their names. Namespaces with processes in them are left alone."""
    out = _ip("netns", "list", check=False)
    removed = []
    for line in out.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        m = re.match(rf"{re.escape(PREFIX)}(\d+)-", name)
        if m and int(m.group(1)) != os.getpid() and not pid_alive(int(m.group(1))) and not _ns_pids(name):
            if _ip("netns", "del", name, check=False).returncode == 0:
                removed.append(name)
    return removed


@dataclass(frozen=True)
class Host:
    """One host of a :class:`Network`.

    :param role: its name in the test (``router``, ``actor``, ...)
    :param ns: its network namespace
    :param addr: its IPv4 address (on :data:`DEV`)
    :param peer: the veth end on the switch's bridge
    """

    role: str
    ns: str
    addr: str
    peer: str


class Network:
    """Hosts (network namespaces) on one switch (a bridge in its own namespace).

    :param roles: the hosts' names, unique; each gets namespace ``khgrl-<pid>-<n>-<role>``
    :param subnet: the first three octets of the /24 (default: from the PID, 10.128-191.X)
    """

    def __init__(self, roles: Sequence[str], subnet: str | None = None) -> None:
        if len(set(roles)) != len(roles) or not roles:
            raise ValueError(f"roles must be unique and non-empty: {list(roles)}")
        if len(roles) > 250:
            raise ValueError("at most 250 hosts on one /24")
        pid, n = os.getpid(), next(_counter)
        self.tag = f"{PREFIX}{pid}-{n}"
        self.subnet = subnet or f"10.{128 + pid % 64}.{(pid // 64 + 37 * n) % 256}"
        self.switch = f"{self.tag}-sw"
        self.hosts = {r: Host(r, f"{self.tag}-{r}", f"{self.subnet}.{i + 1}", f"v{i}") for i, r in enumerate(roles)}
        self.created: list[str] = []  # namespaces that exist (deleted in reverse order)
        self.procs: list[subprocess.Popen] = []
        self._loss_totals: dict[str, dict[str, dict[str, int]]] = {}
        self._loss: dict[str, float] = {}
        self._destroyed = False

    # ------------------------------------------------------------------ set-up and tear-down
    def __enter__(self) -> "Network":
        self.create()
        return self

    def __exit__(self, *exc) -> None:
        self.destroy()

    def create(self) -> None:
        """Make the switch and every host; on any failure, undo what was made and raise :class:`RuntimeError`."""
        remove_stale()
        atexit.register(self.destroy)
        try:
            self._add_ns(self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for h in self.hosts.values():
                self._add_ns(h.ns)
                _ip("link", "add", DEV, "netns", h.ns, "type", "veth", "peer", "name", h.peer, "netns", self.switch)
                _ip("-n", self.switch, "link", "set", h.peer, "master", "br0", "up")
                _ip("-n", h.ns, "addr", "add", f"{h.addr}/24", "dev", DEV)
                _ip("-n", h.ns, "link", "set", DEV, "up")
        except Exception:
            self.destroy()
            raise

    def _add_ns(self, ns: str) -> None:
        _ip("netns", "add", ns)
        self.created.append(ns)
        _ip("-n", ns, "link", "set", "lo", "up")

    def destroy(self) -> dict[str, list[int]]:
        """Kill every process in the namespaces by PID (those started here first), then delete the namespaces.
        Safe to call more than once; returns the PIDs killed per namespace (normally none: the test stopped them)."""
        if self._destroyed:
            return {}
        self._destroyed = True
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    pass
        killed = {}
        for ns in reversed(self.created):
            pids = _kill_ns_processes(ns)
            if pids:
                killed[ns] = pids
            _ip("netns", "del", ns, check=False)
        self.created = []
        atexit.unregister(self.destroy)
        return killed

    # ------------------------------------------------------------------ hosts and processes
    def addr(self, role: str) -> str:
        """The IPv4 address of host ``role``."""
        return self.hosts[role].addr

    def argv(self, role: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside host ``role``'s namespace (``ip netns exec`` execs it: the PID is the command's)."""
        return ["ip", "netns", "exec", self.hosts[role].ns, *argv]

    def run_in(self, role: str, argv: Sequence[str], **popen_kw) -> subprocess.Popen:
        """Start ``argv`` in host ``role``'s namespace; killed by :meth:`destroy` if still running.

        :param role: the host
        :param argv: the command
        :param popen_kw: passed to :class:`subprocess.Popen` (stdout, env, cwd, ...)
        """
        p = subprocess.Popen(self.argv(role, argv), **popen_kw)
        self.procs.append(p)
        return p

    def exec(self, role: str, argv: Sequence[str], timeout: float = 20.0) -> subprocess.CompletedProcess:
        """Run ``argv`` in host ``role``'s namespace to completion (output captured; raises when it fails)."""
        return _run(self.argv(role, argv), timeout=timeout)

    # ------------------------------------------------------------------ faults
    def link_down(self, role: str) -> None:
        """Take host ``role``'s link down (its end: ``ip link set eth0 down`` in its namespace)."""
        _ip("-n", self.hosts[role].ns, "link", "set", DEV, "down")

    def link_up(self, role: str) -> None:
        """Bring host ``role``'s link back up."""
        _ip("-n", self.hosts[role].ns, "link", "set", DEV, "up")

    def set_loss(self, role: str, percent: float) -> None:
        """Drop ``percent`` % of the packets host ``role`` receives and sends on its link, at random (nftables
        ``numgen``; 0 removes the rules). Replacing the rules keeps the counts (:meth:`loss_stats`).

        :param role: the host
        :param percent: 0-100, whole numbers (``numgen random mod 100 < N``)
        """
        n = int(round(percent))
        if not 0 <= n <= 100:
            raise ValueError(f"loss must be 0-100 %, not {percent}")
        self._bank(role)
        if self._loss.pop(role, None) is not None:
            self.exec(role, ["nft", "delete", "table", "inet", LOSS_TABLE])
        if n == 0:
            return
        net = f"{self.subnet}.0/24"
        rules = []
        for chain, hook, iface, match in (("input", "input", "iifname", "saddr"),
                                          ("output", "output", "oifname", "daddr")):
            sel = f'{iface} "{DEV}" ip {match} {net}'
            rules.append(f"  chain {chain} {{\n    type filter hook {hook} priority 0; policy accept;\n"
                         f"    {sel} counter\n    {sel} numgen random mod 100 < {n} counter drop\n  }}")
        script = f"table inet {LOSS_TABLE} {{\n" + "\n".join(rules) + "\n}\n"
        _run(self.argv(role, ["nft", "-f", "-"]), stdin=script)
        self._loss[role] = percent

    def _counters(self, role: str) -> dict[str, dict[str, int]]:
        """The loss rules' counts now: {"in"/"out": {"packets": seen, "dropped": dropped}} (zeros without rules)."""
        out = {"in": {"packets": 0, "dropped": 0}, "out": {"packets": 0, "dropped": 0}}
        if role not in self._loss:
            return out
        doc = json.loads(self.exec(role, ["nft", "-j", "list", "table", "inet", LOSS_TABLE]).stdout)
        for item in doc.get("nftables", []):
            rule = item.get("rule")
            if not rule:
                continue
            way = "in" if rule["chain"] == "input" else "out"
            exprs = rule.get("expr", [])
            packets = next((e["counter"]["packets"] for e in exprs if "counter" in e), 0)
            drops = any("drop" in e for e in exprs)
            out[way]["dropped" if drops else "packets"] += packets
        return out

    def _bank(self, role: str) -> None:
        """Add the current rules' counts to the totals (before the rules are replaced or removed)."""
        now = self._counters(role)
        tot = self._loss_totals.setdefault(role, {w: {"packets": 0, "dropped": 0} for w in ("in", "out")})
        for way in now:
            for k in now[way]:
                tot[way][k] += now[way][k]

    def loss_stats(self, role: str) -> dict[str, dict[str, int]]:
        """Packets on host ``role``'s link that met the loss rules and how many of them were dropped, per
        direction, over all :meth:`set_loss` calls: ``{"in": {"packets", "dropped"}, "out": {...}}``."""
        now = self._counters(role)
        tot = self._loss_totals.get(role, {w: {"packets": 0, "dropped": 0} for w in ("in", "out")})
        return {w: {k: tot[w][k] + now[w][k] for k in now[w]} for w in now}
