"""Access control for a secure KhGRL router: who may publish what, by the common name (CN) of the certificate each
process presents over mutual TLS (Zenoh's ``access_control`` with ``cert_common_names`` subjects; the router's
configuration, see ``deploy/zenoh/secure-router.json5``).

Default deny. Every authenticated process may subscribe, query and receive everything under ``khgrl/**`` (a
monitor does only that). On top of that, by role (``<run>`` is any run id):

=========  ==============================================================================================
role       may publish (put; declare queryables and reply; liveliness tokens)
=========  ==============================================================================================
learner    ``<run>/learner/**`` (weights, acks), its status, task and liveliness (``.../learner/<id>/**``);
           answers queries on ``<run>/learner/weights`` and its task key
actor      ``<run>/actor/<id>/**`` (transitions, frames, episodes, scale, checkpoint requests) under its own
           id only, its status, task and liveliness; answers queries on its task key
human      ``<run>/human/<id>/**`` (corrections) under its own id only, its status and liveliness
launcher   ``<run>/control/**`` (stop, pause, resume, checkpoint), its status and liveliness
monitor    nothing
=========  ==============================================================================================

Zenoh ids are not authenticated, so subjects are certificate common names only (``common/delivery/acl.py`` is the one
place
the rules are written; the router's file is generated from it by ``khgrl certs configs``).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ROLES", "Identity", "access_control", "cn_for"]

ROLES = ("learner", "actor", "human", "monitor", "launcher", "router")
ANY_RUN = "khgrl/*"
# what every authenticated subject may do: declare its interest and ask (ingress), and receive anything (egress)
_READ = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"]
_DELIVER = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable", "liveliness_token",
            "declare_liveliness_subscriber", "liveliness_query"]


def cn_for(role: str, ident: str | None = None) -> str:
    """The certificate common name of a process: ``<role>-<id>``, or ``<role>`` when the id is the role's name
    (or not given): ``actor-a0``, ``human-scripted``, ``learner``, ``launcher``, ``router``.

    :param role: one of :data:`ROLES`
    :param ident: the process's id
    """
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    return role if ident in (None, "", role) else f"{role}-{ident}"


@dataclass(frozen=True)
class Identity:
    """One process on the network: its role, id and certificate common name."""

    role: str
    ident: str

    @property
    def cn(self) -> str:
        return cn_for(self.role, self.ident)


def _publish_keys(role: str, ident: str) -> dict[str, list[str]]:
    """Key expressions a role may put on, answer queries on and hold liveliness tokens on."""
    r = ANY_RUN
    own_status, own_alive = f"{r}/status/{role}/{ident}", [f"{r}/alive/{role}/{ident}", f"{r}/alive/{role}/{ident}/**"]
    if role == "learner":
        return {"put": [f"{r}/learner/**", own_status, f"{r}/task/learner/{ident}"],
                "reply": [f"{r}/learner/weights", f"{r}/task/learner/{ident}"], "token": own_alive}
    if role == "actor":
        return {"put": [f"{r}/actor/{ident}/**", own_status, f"{r}/task/actor/{ident}"],
                "reply": [f"{r}/task/actor/{ident}"], "token": own_alive}
    if role == "human":
        return {"put": [f"{r}/human/{ident}/**", own_status], "reply": [], "token": own_alive}
    if role == "launcher":
        return {"put": [f"{r}/control/**", f"{r}/status/launcher/**"], "reply": [],
                "token": [f"{r}/alive/launcher/**"]}
    return {"put": [], "reply": [], "token": []}  # monitor, router: read only


def _rules_for(ident: Identity) -> list[dict]:
    keys = _publish_keys(ident.role, ident.ident)
    rules = []
    if keys["put"]:
        rules.append({"id": f"{ident.cn}/put", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
                      "key_exprs": keys["put"]})
    if keys["reply"]:
        rules.append({"id": f"{ident.cn}/reply", "permission": "allow", "flows": ["ingress"],
                      "messages": ["declare_queryable", "reply"], "key_exprs": keys["reply"]})
    if keys["token"]:
        rules.append({"id": f"{ident.cn}/alive", "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": keys["token"]})
    return rules


def access_control(identities: list[Identity]) -> dict:
    """The router's ``access_control`` section for these identities (default deny; module docstring).

    :param identities: every process that may join (its certificate's CN is its subject)
    """
    unique = {i.cn: i for i in identities if i.role != "router"}
    if not unique:
        raise ValueError("access control needs at least one identity besides the router")
    rules = [{"id": "read", "permission": "allow", "flows": ["ingress"], "messages": _READ, "key_exprs": ["khgrl/**"]},
             {"id": "deliver", "permission": "allow", "flows": ["egress"], "messages": _DELIVER,
              "key_exprs": ["khgrl/**"]}]
    subjects = [{"id": cn, "cert_common_names": [cn]} for cn in sorted(unique)]
    policies = [{"id": "everyone", "rules": ["read", "deliver"], "subjects": sorted(unique)}]
    for cn in sorted(unique):
        own = _rules_for(unique[cn])
        rules += own
        if own:
            policies.append({"id": f"{cn}/own", "rules": [r["id"] for r in own], "subjects": [cn]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
