"""The delivery layer's boundary, checked on the source: only the modules listed in
:data:`khgrl.common.delivery.ZENOH_MODULES` import ``zenoh``; key expressions are parsed (``Keys.chunk``) only inside
``common/delivery``; the actor's and learner's loops stay short and name no Zenoh declaration."""

from __future__ import annotations

import ast
from pathlib import Path

from khgrl.common.delivery import ZENOH_MODULES

from test_protocol import imports_package

REPO = Path(__file__).resolve().parents[2]
FOLDERS = ("khgrl", "common", "actor", "learner", "human_bridge", "deploy", "benchmarks")
ZENOH_CALLS = {"declare_subscriber", "declare_publisher", "declare_queryable", "declare_token", "liveliness"}


def _sources() -> dict[str, ast.AST]:
    out = {}
    for folder in FOLDERS:
        for path in (REPO / folder).rglob("*.py"):
            out[path.relative_to(REPO).as_posix()] = ast.parse(path.read_text())
    return out


def _imports_zenoh(tree: ast.AST) -> bool:
    return imports_package(tree, "zenoh")


def _attribute_calls(tree: ast.AST, names: set[str]) -> list[str]:
    return [node.func.attr for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in names]


def test_only_the_listed_modules_import_zenoh():
    sources = _sources()
    assert all(m in sources for m in ZENOH_MODULES), [m for m in ZENOH_MODULES if m not in sources]
    importing = sorted(path for path, tree in sources.items() if _imports_zenoh(tree))
    assert importing == sorted(ZENOH_MODULES)


def test_the_processes_declare_nothing_on_a_zenoh_session_themselves():
    """The actor, learner, human-input clients and launcher declare through the delivery layer."""
    for path, tree in _sources().items():
        if path.startswith(("actor/", "learner/", "human_bridge/")) or path == "deploy/run/launcher.py":
            assert not _attribute_calls(tree, ZENOH_CALLS), f"{path} declares on a Zenoh session"


def test_key_expressions_are_parsed_only_in_the_delivery_layer():
    for path, tree in _sources().items():
        if path.startswith("common/delivery/") or path == "common/wire/protocol.py":
            continue
        parses = [node for node in ast.walk(tree) if isinstance(node, ast.Attribute)
                  and node.attr in ("chunk", "last_chunk")
                  and isinstance(node.value, ast.Name) and node.value.id == "Keys"]
        assert not parses, f"{path} parses a key expression"


def test_the_loops_read_top_to_bottom():
    """The actor's and learner's loops leave delivery to the layer: about 200 lines each, no Zenoh declaration, no
    key expression."""
    for path in ("actor/loop.py", "learner/loop.py"):
        text = (REPO / path).read_text()
        tree = ast.parse(text)
        assert len(text.splitlines()) <= 230, f"{path}: {len(text.splitlines())} lines"
        assert not _imports_zenoh(tree) and not _attribute_calls(tree, ZENOH_CALLS), path
        assert not [n for n in ast.walk(tree) if isinstance(n, ast.Name) and n.id == "Keys"], f"{path} uses Keys"
