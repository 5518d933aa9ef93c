"""The secure router's access control, through a real Zenoh router made from ``khgrl certs configs``: each identity
publishes exactly its own keys (a monitor receives what got through), liveliness tokens and queryables cannot be
spoofed, and processes without a certificate of the run's CA cannot connect at all."""

from __future__ import annotations

import json
import time

import pytest
from khgrl.common.delivery.transport import _open, free_port
from khgrl.common.delivery.zenoh_config import build_config
from khgrl.deploy.run import certs
from khgrl.deploy.run.secure import issue_identities, write_configs

pytestmark = pytest.mark.integration

IDS = [("router", None), ("learner", None), ("launcher", None), ("actor", "a0"), ("actor", "a1"), ("human", "h0"),
       ("monitor", None)]
R = "khgrl/r1"
# (publisher, key, delivered?)
MATRIX = [
    ("learner", f"{R}/learner/weights", True), ("learner", f"{R}/learner/ack/a0", True),
    ("learner", f"{R}/status/learner/learner", True), ("learner", f"{R}/actor/a0/transitions", False),
    ("actor-a0", f"{R}/actor/a0/transitions", True), ("actor-a0", f"{R}/actor/a0/request", True),
    ("actor-a0", f"{R}/status/actor/a0", True), ("actor-a0", f"{R}/task/actor/a0", True),
    ("actor-a0", f"{R}/learner/weights", False), ("actor-a0", f"{R}/learner/ack/a0", False),
    ("actor-a1", f"{R}/actor/a0/transitions", False), ("actor-a0", f"{R}/actor/evil/transitions", False),
    ("actor-a0", f"{R}/control/all", False), ("actor-a0", f"{R}/human/h0/correction", False),
    ("actor-a0", f"{R}/status/learner/learner", False),
    ("human-h0", f"{R}/human/h0/correction", True), ("human-h0", f"{R}/human/h1/correction", False),
    ("human-h0", f"{R}/control/all", False), ("human-h0", f"{R}/learner/weights", False),
    ("launcher", f"{R}/control/all", True), ("launcher", f"{R}/learner/weights", False),
    ("monitor", f"{R}/learner/weights", False), ("monitor", f"{R}/control/all", False),
    ("monitor", f"{R}/actor/a0/transitions", False),
]


@pytest.fixture(scope="module")
def secure_router(tmp_path_factory):
    d = issue_identities(tmp_path_factory.mktemp("acl") / "certs", IDS)
    ep = f"tls/127.0.0.1:{free_port()}"
    files = write_configs(d, ep, ep)
    router = _open(build_config("router", [ep], [], 3000, files["router"]), lambda: False, 20, "router")
    sessions = {cn: _open(build_config("client", [], [ep], 3000, files[cn]), lambda: False, 20, cn)
                for cn in files if cn != "router"}
    yield d, ep, sessions
    for s in sessions.values():
        s.close()
    router.close()


def _wait(pred, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def test_each_identity_publishes_only_its_own_keys(secure_router):
    _, _, s = secure_router
    got: list[str] = []
    import zenoh

    # remote only: a session's own puts reach its own subscribers without crossing the router
    sub = s["monitor"].declare_subscriber("khgrl/**", lambda x: got.append(x.payload.to_bytes().decode()),
                                          allowed_origin=zenoh.Locality.REMOTE)
    time.sleep(0.5)
    for n, (who, key, _) in enumerate(MATRIX):
        s[who].put(key, str(n).encode())
    assert _wait(lambda: sum(1 for *_, ok in MATRIX if ok) <= len(got), 5.0)
    time.sleep(0.5)  # anything that should not arrive has had as long as what did
    sub.undeclare()
    wrong = [(who, key, ok) for n, (who, key, ok) in enumerate(MATRIX) if (str(n) in got) != ok]
    assert not wrong, f"delivered when it should not be (True) / dropped when allowed (False): {wrong}"


def test_liveliness_and_queryables_cannot_be_spoofed(secure_router):
    _, _, s = secure_router
    fake = s["actor-a0"].liveliness().declare_token(f"{R}/alive/learner/learner/e0")
    real = s["learner"].liveliness().declare_token(f"{R}/alive/learner/learner/e1")
    mine = s["actor-a0"].liveliness().declare_token(f"{R}/alive/actor/a0")
    q_fake = s["actor-a0"].declare_queryable(f"{R}/learner/weights", lambda q: q.reply(f"{R}/learner/weights", b"f"))
    q_real = s["learner"].declare_queryable(f"{R}/learner/weights", lambda q: q.reply(f"{R}/learner/weights", b"w"))
    time.sleep(1.0)
    alive = sorted(str(r.ok.key_expr) for r in s["monitor"].liveliness().get(f"{R}/alive/**", timeout=2.0) if r.ok)
    replies = [r.ok.payload.to_bytes() for r in s["monitor"].get(f"{R}/learner/weights", timeout=2.0) if r.ok]
    for d in (fake, real, mine, q_fake, q_real):
        d.undeclare()
    assert alive == [f"{R}/alive/actor/a0", f"{R}/alive/learner/learner/e1"]
    assert replies == [b"w"]


def _refused(conf) -> bool:
    conf.insert_json5("connect/timeout_ms", "0")
    conf.insert_json5("connect/exit_on_failure", "true")
    try:
        _open(conf, lambda: False, 10, "attacker").close()
    except ConnectionError:
        return True
    return False


def test_without_a_certificate_of_the_ca_nobody_connects(secure_router, tmp_path):
    d, ep, _ = secure_router
    plain = build_config("client", [], [ep.replace("tls/", "tcp/")], 3000)
    assert _refused(plain), "plain TCP to the TLS port"
    no_cert = build_config("client", [], [ep.replace("tls/", "tcp/")], 3000)
    no_cert.insert_json5("connect/endpoints", f'["{ep}"]')
    no_cert.insert_json5("transport/link/tls/root_ca_certificate", f'"{d / "ca.pem"}"')
    assert _refused(no_cert), "TLS without a client certificate"
    other = tmp_path / "other"
    certs.init_ca(other)
    certs.issue(other, "learner")
    forged = build_config("client", [], [ep.replace("tls/", "tcp/")], 3000)
    forged.insert_json5("connect/endpoints", f'["{ep}"]')

    tls = certs.tls_settings((d / "ca.pem", other / "learner.pem", other / "learner.key"), "learner", listen=False)
    forged.insert_json5("transport/link/tls", json.dumps(tls))
    assert _refused(forged), "a learner certificate from another CA"
