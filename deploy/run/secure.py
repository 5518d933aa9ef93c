"""Zenoh configuration files for a secure deployment, made from a certificate directory (``khgrl certs``): the
router's (TLS listener, mutual TLS, access control per identity: :mod:`khgrl.common.delivery.acl`) and one per process
identity
(its certificate and key, the CA). ``khgrl certs configs DIR`` writes them for machines on a network;
``khgrl up --secure`` makes a CA, the run's identities and these files in ``RUN_DIR/certs`` and starts every
process with its own.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from khgrl.common.config.settings import HUMAN_METHODS
from khgrl.common.delivery.acl import Identity, access_control
from khgrl.deploy.run import certs

__all__ = ["SecureRun", "router_settings", "client_settings", "write_configs", "prepare_secure_run",
           "add_configs_parser", "run_identities", "issue_identities"]

CONFIG_DIR = "zenoh"  # under the certificate directory
EXTRA_IDS = (("human", "user"), ("monitor", "monitor"))  # for a client the user plugs in, and for watching


def router_settings(cert_dir: Path, listen: str, identities: list[Identity]) -> dict:
    """The router's Zenoh configuration: listen on ``listen`` (a ``tls/`` endpoint) with its certificate, demand
    client certificates from the directory's CA, and allow each identity only its own keys.

    :param cert_dir: the certificate directory (``ca.pem``, ``router.pem``, ``router.key``)
    :param listen: the endpoint, e.g. ``tls/0.0.0.0:7447``
    :param identities: the processes that may join
    """
    tls = certs.tls_settings(cert_dir, "router", listen=True)
    tls.pop("verify_name_on_connect", None)
    return {"mode": "router", "listen": {"endpoints": [listen]}, "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tls": tls}}, "access_control": access_control(identities)}


def client_settings(cert_dir: Path, cn: str, connect: str) -> dict:
    """A process's Zenoh configuration: connect to the router at ``connect`` with this identity's certificate.

    :param cert_dir: the certificate directory
    :param cn: the identity's common name (``actor-a0``)
    :param connect: the router's endpoint, e.g. ``tls/192.168.1.10:7447``
    """
    return {"mode": "client", "connect": {"endpoints": [connect]}, "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tls": certs.tls_settings(cert_dir, cn, listen=False)}}}


def _write_json5(path: Path, settings: dict, what: str) -> None:
    header = (f"// {what}\n// Made by khgrl from the certificates in {path.parent.parent}; KhGRL merges its required "
              f"settings (mode, endpoints, scouting off) over this file.\n")
    path.write_text(header + json.dumps(settings, indent=2) + "\n")
    os.chmod(path, 0o644)


def write_configs(cert_dir: str | os.PathLike, listen: str, connect: str) -> dict[str, Path]:
    """Write ``DIR/zenoh/router.json5`` and ``DIR/zenoh/<cn>.json5`` for every identity issued in ``DIR``.

    :param cert_dir: the certificate directory (CA and issued identities)
    :param listen: the router's listening endpoint (``tls/0.0.0.0:7447``)
    :param connect: the endpoint clients connect to (``tls/ROUTER-ADDRESS:7447``)
    :return: {common name: configuration file}
    """
    d = Path(cert_dir)
    found = certs.identities(d)
    ids = [Identity(i.role, i.id) for i in found]
    if not any(i.role == "router" for i in ids):
        raise certs.CertError(f"{d} has no router certificate: khgrl certs issue {d} --role router --host ADDRESS")
    out = d / CONFIG_DIR
    out.mkdir(mode=0o755, exist_ok=True)
    files = {"router": out / "router.json5"}
    _write_json5(files["router"], router_settings(d, listen, ids), "the KhGRL router: khgrl router --zenoh-config "
                                                                  "THIS --listen " + listen)
    for i in found:
        if i.role == "router" or i.key is None:
            continue
        files[i.cn] = out / f"{i.cn}.json5"
        _write_json5(files[i.cn], client_settings(d, i.cn, connect), f"{i.cn}: --zenoh-config THIS")
    return files


@dataclass
class SecureRun:
    """The secure setup of one ``khgrl up --secure``: where each process's Zenoh configuration is."""

    cert_dir: Path
    files: dict[str, Path]

    def config_for(self, role: str, ident: str | None = None) -> str:
        """The configuration file of a process (``role``, ``ident``)."""
        return str(self.files[certs.cn_for(role, ident)])


def run_identities(cfg) -> list[tuple[str, str]]:
    """(role, id) of every process ``khgrl up`` starts besides the router and itself.

    :param cfg: the run's :class:`~khgrl.common.config.settings.RunConfig`
    """
    ids = [("learner", "learner")] + [("actor", a) for a in cfg.actor_ids()]
    if cfg.method in HUMAN_METHODS and cfg.human != "none":
        ids.append(("human", cfg.human))
    return ids


def issue_identities(cert_dir: str | os.PathLike, identities: list[tuple[str, str | None]],
                     router_hosts: tuple[str, ...] = ()) -> Path:
    """A CA in ``cert_dir`` (unless it has one) and a certificate for each (role, id) it does not have yet.

    :param cert_dir: the certificate directory
    :param identities: (role, id) pairs; ``("router", ...)`` gets ``router_hosts`` as its names
    :param router_hosts: the router's addresses and names (default: 127.0.0.1 and localhost)
    """
    d = Path(cert_dir)
    if not (d / certs.CA_CERT).is_file():
        certs.init_ca(d)
    for role, ident in identities:
        if not (d / f"{certs.cn_for(role, ident)}.pem").is_file():
            certs.issue(d, role, ident, hosts=router_hosts if role == "router" else ())
    return d


def prepare_secure_run(run_dir: Path, endpoint: str, processes: list[tuple[str, str]]) -> SecureRun:
    """``RUN_DIR/certs``: a CA for this run, a certificate for the router, the launcher, each process in
    ``processes`` and the extra identities (``human-user``, ``monitor``), and their Zenoh configurations. An
    existing directory (``--resume``) keeps its CA and certificates and gets the missing ones.

    :param run_dir: the run directory
    :param endpoint: the router's ``tls/`` endpoint on this machine
    :param processes: (role, id) of the learner, actors and human-input client
    """
    d = issue_identities(run_dir / "certs", [("router", "router"), ("launcher", "launcher"), *processes, *EXTRA_IDS])
    return SecureRun(d, write_configs(d, endpoint, endpoint))


def _cmd_configs(args: argparse.Namespace) -> int:
    connect = args.connect or args.listen.replace("0.0.0.0", "127.0.0.1")
    files = write_configs(args.dir, args.listen, connect)
    print(f"router: khgrl router --zenoh-config {files.pop('router')} --listen {args.listen}")
    for cn, path in files.items():
        print(f"{cn}: --zenoh-config {path}")
    print(f"(clients connect to {connect}; the router lets each identity publish only its own keys)")
    return 0


def add_configs_parser(certs_sub: Any) -> None:
    """``khgrl certs configs DIR``: the router's and every identity's Zenoh configuration from DIR.

    :param certs_sub: the subcommands of ``khgrl certs``
    """
    p = certs_sub.add_parser("configs", help="write DIR/zenoh/router.json5 (mutual TLS + access control for every "
                                             "identity in DIR) and DIR/zenoh/<cn>.json5 for each identity")
    p.add_argument("dir", metavar="DIR", help="certificate directory (CA, router and process certificates)")
    p.add_argument("--listen", default="tls/0.0.0.0:7447",
                   help="the router's listening endpoint (default: %(default)s)")
    p.add_argument("--connect", default=None,
                   help="the endpoint clients connect to, e.g. tls/192.168.1.10:7447: an address or name in the "
                        "router certificate's --host list (default: --listen with 0.0.0.0 as 127.0.0.1)")
    p.set_defaults(func=_cmd_configs)
