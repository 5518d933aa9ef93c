"""``khgrl router``: a Zenoh router (zenoh-python in router mode, no other binary) until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import sys

from common.process import StopFlag, die_with_parent, install_stop_handlers
from common.transport import DEFAULT_ENDPOINT, open_router

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl router", description="Run a Zenoh router for KhGRL processes.")
    p.add_argument("--listen", default=DEFAULT_ENDPOINT, help="endpoint to listen on (default %(default)s)")
    p.add_argument("--lease-ms", type=int, default=3000, help="link lease in ms (default %(default)s)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    die_with_parent()
    flag = StopFlag()
    install_stop_handlers(flag)
    try:
        session = open_router(args.listen, args.lease_ms)
    except ConnectionError as exc:
        print(f"khgrl router: error: {exc}", file=sys.stderr, flush=True)
        return 2
    with session:
        print(f"khgrl router {session.zid()} listening on {args.listen}", flush=True)
        while not flag.wait(0.2):
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
