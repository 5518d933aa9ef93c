"""``khgrl keys``: the run's signing keys, one per process, for processes started by hand (``khgrl up`` makes them
itself): docs/protocol.md, "Who may press, release, stop and confirm ready".

    khgrl keys RUN_DIR                          # the operator, and the learner, actors and human client of
                                                #   RUN_DIR/config.json (if there): those without a key get one
    khgrl keys RUN_DIR --actor a0 --actor a1 --human gui   # more ids (a client added while the run goes on)
    khgrl keys RUN_DIR --list                   # what RUN_DIR/keys/public.json holds

It writes ``RUN_DIR/keys/public.json`` (every public key) and ``RUN_DIR/keys/<role>-<id>.key`` (each private key,
mode 0600). Across machines, copy ``public.json`` into each machine's run directory and each private key only to the
machine that runs that process (the operator's, ``operator-launcher.key``, to where ``khgrl stop`` runs, or pass it
with ``khgrl stop --key``). An existing key is kept unless ``--fresh``.

Exit codes: 0 done; 2 a bad argument (a bad id, a file that is not a key table).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from khgrl.common.delivery.role_keys import PublicKeys, RoleKeyError, key_id, make_keys, private_path

__all__ = ["main", "build_parser", "wanted"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl keys", description="Make the run's signing keys (one per process) for "
                                "processes started by hand; khgrl up makes its own.")
    p.add_argument("run_dir", metavar="RUN_DIR", help="the run directory (keys go to RUN_DIR/keys)")
    p.add_argument("--actor", action="append", default=[], metavar="ID", help="an actor id (repeatable; default: "
                   "those of RUN_DIR/config.json, if there)")
    p.add_argument("--human", action="append", default=[], metavar="ID", help="a human-input client id "
                   "(repeatable; default: the one of RUN_DIR/config.json, if there)")
    p.add_argument("--learner", action="append", default=[], metavar="ID", help="a learner id (repeatable; default: "
                   "learner)")
    p.add_argument("--fresh", action="store_true", help="replace the keys of these ids that exist (default: keep them)")
    p.add_argument("--list", action="store_true", help="only list the public keys in RUN_DIR (default: off)")
    return p


def wanted(args: argparse.Namespace) -> list[str]:
    """The key ids to make: the operator, the learner, and the ids of ``RUN_DIR/config.json`` and the flags.

    :param args: the parsed arguments.
    """
    from khgrl.deploy.run.secure import run_identities

    ids = [("learner", i) for i in args.learner or ["learner"]]
    config = Path(args.run_dir) / "config.json"
    if config.is_file():
        from khgrl.common.config.settings import read_run_file

        ids += run_identities(read_run_file(config)[0])
    ids += [("actor", a) for a in args.actor] + [("human", h) for h in args.human]
    kids = [key_id("operator", "launcher")] + [key_id(role, ident) for role, ident in ids]
    return list(dict.fromkeys(kids))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.list:
            for kid, hexkey in PublicKeys.read_table(args.run_dir).items():
                mine = private_path(args.run_dir, kid)
                print(f"{kid:24s} {hexkey}" + (f"  (private key here: {mine})" if mine.is_file() else ""))
            return 0
        kids = wanted(args)
        made = make_keys(args.run_dir, kids, fresh=args.fresh)
    except (RoleKeyError, ValueError, OSError) as exc:
        print(f"khgrl keys: error: {exc}", file=sys.stderr)
        return 2
    for kid in kids:
        print(f"{kid}: {'made' if kid in made else 'kept'} {private_path(args.run_dir, kid)}")
    print(f"khgrl keys: {len(made)} made, {len(kids) - len(made)} kept; public keys in "
          f"{Path(args.run_dir) / 'keys' / 'public.json'} (copy it to every machine of the run, each private key only "
          f"to its process's machine)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
