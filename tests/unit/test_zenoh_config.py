"""Zenoh configuration files (``--zenoh-config``, ``ZENOH_CONFIG``): KhGRL's required settings win over the file
(conflicts reported), its tuning only fills what the file leaves at Zenoh's default, bad files are one clear error,
and the configurations shipped in deploy/zenoh/ load and match what the code generates."""

from __future__ import annotations

import argparse
import json
import logging
import re
from pathlib import Path

import pytest
from khgrl.common.config.process import add_process_flags, resolve_process
from khgrl.common.delivery.acl import Identity, access_control
from khgrl.common.delivery.zenoh_config import ENV, ZenohConfigError, build_config, config_file, identity

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "deploy" / "zenoh"


def _get(conf, key):
    return json.loads(conf.get_json(key))


def test_required_settings_win_and_conflicts_are_reported(tmp_path, caplog):
    f = tmp_path / "z.json5"
    f.write_text('{ // mine\n mode: "peer", connect: { endpoints: ["tcp/10.9.9.9:1"] },\n'
                 ' scouting: { multicast: { enabled: true } }, transport: { link: { tx: { lease: 5000 } } } }')
    with caplog.at_level(logging.WARNING, logger="khgrl.transport"):
        conf = build_config("client", [], ["tcp/127.0.0.1:7447"], 3000, f)
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "scouting/multicast/enabled") is False
    assert _get(conf, "transport/link/tx/lease") == 5000  # the file's own tuning is kept
    assert _get(conf, "transport/shared_memory/enabled") is False  # KhGRL's tuning fills the rest
    warned = " ".join(r.getMessage() for r in caplog.records)
    for key in ("mode", "connect/endpoints", "scouting/multicast/enabled"):
        assert key in warned
    assert "lease" not in warned


def test_no_file_is_the_builtin_configuration():
    conf = build_config("router", ["tcp/127.0.0.1:7447"], [], 2500)
    assert _get(conf, "mode") == "router"
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "transport/link/tx/lease") == 2500
    assert identity(conf).startswith("no certificate")


@pytest.mark.parametrize("text, words", [(None, "does not exist"), ("{ mode: ", "cannot be read"),
                                         ("{ colour: 1 }", "unknown field")])
def test_bad_files_are_one_clear_error(tmp_path, text, words):
    f = tmp_path / "z.json5"
    if text is not None:
        f.write_text(text)
    with pytest.raises(ZenohConfigError, match=words) as exc:
        build_config("client", [], ["tcp/127.0.0.1:7447"], 3000, f)
    assert "\n" not in str(exc.value)


def test_tls_endpoint_without_certificates_says_what_to_do():
    with pytest.raises(ZenohConfigError, match="khgrl certs"):
        build_config("client", [], ["tls/127.0.0.1:7447"], 3000)


def test_environment_variable_is_honoured(tmp_path, monkeypatch):
    f = tmp_path / "z.json5"
    f.write_text("{}")
    monkeypatch.delenv(ENV, raising=False)
    assert config_file(None) is None
    monkeypatch.setenv(ENV, str(f))
    assert config_file(None) == str(f)
    assert config_file("other.json5") == "other.json5"  # the flag wins
    p = argparse.ArgumentParser()
    add_process_flags(p)
    assert resolve_process(p.parse_args(["--run", "r1"])).zenoh_config == str(f)
    assert resolve_process(p.parse_args(["--run", "r1", "--zenoh-config", "x.json5"])).zenoh_config == "x.json5"


@pytest.mark.parametrize("path", sorted(SHIPPED.glob("*.json5")), ids=lambda p: p.name)
def test_shipped_configurations_load(path):
    import zenoh

    zenoh.Config.from_file(str(path))
    mode = "router" if "router" in path.name else "client"
    endpoint = "tcp/127.0.0.1:7447"
    conf = build_config(mode, [endpoint] if mode == "router" else [], [] if mode == "router" else [endpoint],
                        3000, path)
    assert _get(conf, "mode") == mode


def test_shipped_secure_router_matches_the_generated_access_control():
    text = (SHIPPED / "secure-router.json5").read_text()
    settings = json.loads(re.sub(r"^\s*//.*$", "", text, flags=re.M))
    cns = [s["cert_common_names"][0] for s in settings["access_control"]["subjects"]]
    ids = []
    for cn in cns:
        role, _, ident = cn.partition("-")
        ids.append(Identity(role, ident or role))
    assert settings["access_control"] == access_control(ids)
    assert settings["transport"]["link"]["tls"]["enable_mtls"] is True
    clients = {p.name.removeprefix("secure-").removesuffix(".json5") for p in SHIPPED.glob("secure-*.json5")}
    assert clients - {"router"} == set(cns)  # one client configuration per identity the router knows


def test_shared_memory_is_off_unless_a_file_sets_its_section(tmp_path, caplog):
    endpoint = ["tcp/127.0.0.1:7447"]
    assert _get(build_config("client", [], endpoint, 3000), "transport/shared_memory/enabled") is False
    shipped = build_config("client", [], endpoint, 3000, SHIPPED / "shared-memory.json5")
    assert _get(shipped, "transport/shared_memory/enabled") is True
    assert _get(shipped, "transport/shared_memory/transport_optimization/messages") == ["put"]  # zenoh#2628
    f = tmp_path / "z.json5"  # only enabled: true is Zenoh's default, left to KhGRL's tuning (off)
    f.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert _get(build_config("client", [], endpoint, 3000, f), "transport/shared_memory/enabled") is False
    f.write_text("{ transport: { shared_memory: { transport_optimization: { pool_size: 33554432 } } } }")
    with caplog.at_level(logging.WARNING, logger="khgrl.transport"):
        mine = build_config("client", [], endpoint, 3000, f)
    assert _get(mine, "transport/shared_memory/enabled") is True  # the file's own section, queries and replies too
    assert "zenoh#2628" in caplog.text and "query and reply" in caplog.text
