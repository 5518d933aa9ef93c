"""``khgrl router``: a Zenoh router (zenoh-python in router mode, no other binary) until SIGINT/SIGTERM.

With ``--zenoh-config`` it takes a Zenoh configuration file: e.g. ``deploy/zenoh/router.json5`` (plain TCP for
several machines) or the secure one ``khgrl certs configs`` writes (TLS, client certificates, access control)."""

from __future__ import annotations

import argparse
import sys

from khgrl.common.delivery.transport import DEFAULT_ENDPOINT, open_router
from khgrl.common.process import StopFlag, die_with_parent, install_stop_handlers

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl router", description="Run a Zenoh router for KhGRL processes.")
    p.add_argument("--listen", default=DEFAULT_ENDPOINT, help="endpoint to listen on (default %(default)s)")
    p.add_argument("--lease-ms", type=int, default=3000, help="link lease in ms (default %(default)s)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="Zenoh configuration (JSON5: TLS certificates, access control, ...) merged under KhGRL's "
                        "required settings (router mode, --listen, scouting off); deploy/zenoh/ has examples "
                        "(default: $ZENOH_CONFIG if set, else none)")
    return p


def _acl_enabled(file: str | None) -> bool:
    """Whether the router's configuration file turns access control on (for its first log line)."""
    import json

    import zenoh
    from khgrl.common.delivery.zenoh_config import config_file

    path = config_file(file)
    if not path:
        return False
    try:
        return bool(json.loads(zenoh.Config.from_file(path).get_json("access_control/enabled")))
    except Exception:  # noqa: BLE001 - open_router has already reported an unusable file
        return False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    die_with_parent()
    flag = StopFlag()
    install_stop_handlers(flag)
    try:
        session = open_router(args.listen, args.lease_ms, zenoh_config=args.zenoh_config)
    except ConnectionError as exc:
        print(f"khgrl router: error: {exc}", file=sys.stderr, flush=True)
        return 2
    with session:
        acl = "access control on" if _acl_enabled(args.zenoh_config) else "no access control"
        print(f"khgrl router {session.zid()} listening on {args.listen} ({acl})", flush=True)
        while not flag.wait(0.2):
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
