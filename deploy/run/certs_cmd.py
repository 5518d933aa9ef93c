"""``khgrl certs init | issue | list``: the command line of :mod:`khgrl.deploy.run.certs` (``configs`` is added by
:mod:`khgrl.deploy.run.secure`)."""

from __future__ import annotations

import argparse
from typing import Any

from cryptography import x509
from khgrl.deploy.run.certs import (
    DEFAULT_DAYS,
    DEFAULT_HOSTS,
    ROLES,
    common_name,
    expires,
    identities,
    init_ca,
    issue,
    load_cert,
)


def _cmd_init(args: argparse.Namespace) -> int:
    cert, key = init_ca(args.dir, days=args.days, force=args.force)
    print(f"CA {common_name(cert)!r} in {cert} (key {key}, keep it private), valid until {expires(cert):%Y-%m-%d}")
    return 0


def _cmd_issue(args: argparse.Namespace) -> int:
    cert, key = issue(args.dir, args.role, args.id, hosts=args.host or (), days=args.days, force=args.force)
    print(f"{common_name(cert)}: {cert} and {key}, valid until {expires(cert):%Y-%m-%d}")
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    rows = [("ROLE", "ID", "CN", "EXPIRES", "KEY", "NAMES")]
    for i in identities(args.dir):
        cert = load_cert(i.cert)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        names = ",".join(str(n.value) for n in san)
        rows.append((i.role, i.id, i.cn, f"{expires(i.cert):%Y-%m-%d}", "yes" if i.key else "no", names))
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    for r in rows:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip())
    if len(rows) == 1:
        print(f"(no identities in {args.dir})")
    return 0


def add_parser(sub: Any) -> Any:
    """Register ``khgrl certs`` on the subcommands ``sub`` of the ``khgrl`` parser; returns its own subcommands
    (where :mod:`khgrl.deploy.run.secure` adds ``configs``).

    :param sub: the ``add_subparsers()`` object.
    """
    top = sub.add_parser("certs", help="certificates for mutual TLS: a CA, one key + certificate per identity")
    certs = top.add_subparsers(dest="action", required=True, metavar="ACTION")
    p = certs.add_parser("init", help="make a CA in DIR (ca.pem, ca.key; DIR mode 0700, key mode 0600)")
    p.add_argument("dir", metavar="DIR", help="certificate directory (created if missing)")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, help="validity in days (default: %(default)s)")
    p.add_argument("--force", action="store_true", help="replace an existing CA (default: refuse)")
    p.set_defaults(func=_cmd_init)
    p = certs.add_parser("issue", help="make DIR/<cn>.pem and DIR/<cn>.key (unencrypted PKCS#8, mode 0600) for one "
                                       "identity, signed by the CA in DIR; cn = ROLE-ID, or ROLE when ID is ROLE")
    p.add_argument("dir", metavar="DIR", help="certificate directory with the CA")
    p.add_argument("--role", required=True, help=f"one of: {', '.join(ROLES)} (required)")
    p.add_argument("--id", default=None,
                   help="process id: 1-64 printable ASCII characters, no / * $ ? # or space (default: the role, "
                        "e.g. 'learner')")
    p.add_argument("--host", action="append", default=None, metavar="H",
                   help="router only, repeatable: an IP address or DNS name clients connect to "
                        f"(default: {' and '.join(DEFAULT_HOSTS)})")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS,
                   help="validity in days, cut to the CA's (default: %(default)s)")
    p.add_argument("--force", action="store_true", help="replace an existing identity (default: refuse)")
    p.set_defaults(func=_cmd_issue)
    p = certs.add_parser("list", help="the identities whose certificates are in DIR, with expiry")
    p.add_argument("dir", metavar="DIR", help="certificate directory")
    p.set_defaults(func=_cmd_list)
    return certs
