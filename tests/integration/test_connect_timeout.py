"""``--connect-timeout`` on every process (issue 20, newcomer defect 5): ``khgrl actor --connect tcp/...`` against a
TLS router used to hang without a word (Zenoh retries a handshake the router never completes). Each process --
actor, learner, a human-input client -- is started for real against a real router that speaks only ``tls/``
(certificates from :func:`khgrl.deploy.run.secure.issue_identities`), and against a port nobody listens on: it must
exit with code 1 within its connect timeout (plus its start-up), with one error line naming the endpoint and the
flag.
"""

from __future__ import annotations

import subprocess
import time

import pytest
from khgrl.common.delivery.transport import free_port, wait_reachable
from khgrl.deploy.run.secure import issue_identities, write_configs
from khgrl.deploy.run.supervisor import khgrl_argv

pytestmark = pytest.mark.integration

TIMEOUT_S = 3
# (name, argv after "khgrl", the line's prefix on stderr)
PROCESSES = [
    ("actor", ["actor", "--id", "a0"], "khgrl actor a0: error: "),
    ("learner", ["learner"], "khgrl learner: error: "),
    ("human", ["human", "scripted"], "khgrl human scripted: "),
]


@pytest.fixture(scope="module")
def tls_router(tmp_path_factory):
    """A real ``khgrl router`` listening only on ``tls/`` (mutual TLS, access control): the endpoint a ``tcp/``
    client would be given by mistake."""
    d = issue_identities(tmp_path_factory.mktemp("tls") / "certs", [("router", None), ("actor", "a0")])
    port = free_port()
    files = write_configs(d, f"tls/127.0.0.1:{port}", f"tls/127.0.0.1:{port}")
    router = subprocess.Popen(khgrl_argv("router", "--listen", f"tls/127.0.0.1:{port}", "--zenoh-config",
                                         str(files["router"])), stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        wait_reachable(f"tcp/127.0.0.1:{port}", 30)  # it accepts TCP connections; it completes only TLS handshakes
        yield f"tcp/127.0.0.1:{port}"
    finally:
        router.terminate()
        router.wait(10)


def _start(argv: list[str], endpoint: str, run_dir) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    proc = subprocess.run(khgrl_argv(*argv, "--run", "ct", "--connect", endpoint, "--run-dir", str(run_dir),
                                     "--connect-timeout", str(TIMEOUT_S)),
                          capture_output=True, text=True, timeout=90)
    return proc, time.monotonic() - t0


def _check(proc: subprocess.CompletedProcess, took: float, prefix: str, endpoint: str) -> None:
    assert proc.returncode == 1, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith(prefix)]
    assert len(lines) == 1, f"expected one error line starting {prefix!r}:\n{proc.stderr}"
    line = lines[0]
    assert f"at {endpoint} within {TIMEOUT_S} s (--connect-timeout)" in line, line
    assert "Traceback" not in proc.stderr, proc.stderr
    assert took < TIMEOUT_S + 45, f"took {took:.0f} s with a connect timeout of {TIMEOUT_S} s"


@pytest.mark.timeout(150)
@pytest.mark.parametrize("name,argv,prefix", PROCESSES, ids=[p[0] for p in PROCESSES])
def test_a_tcp_client_of_a_tls_router_fails_with_one_line_within_the_connect_timeout(tls_router, tmp_path, name,
                                                                                      argv, prefix):
    proc, took = _start(argv, tls_router, tmp_path / "run")
    _check(proc, took, prefix, tls_router)


@pytest.mark.timeout(150)
@pytest.mark.parametrize("name,argv,prefix", PROCESSES, ids=[p[0] for p in PROCESSES])
def test_no_router_listening_fails_with_one_line_within_the_connect_timeout(tmp_path, name, argv, prefix):
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there
    proc, took = _start(argv, endpoint, tmp_path / "run")
    _check(proc, took, prefix, endpoint)
