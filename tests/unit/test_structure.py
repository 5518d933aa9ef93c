"""The code's shape, checked: one installed package (``khgrl``) whose subpackages are the top-level folders, no
import cycles between first-party modules nor between packages, no module over 400 lines, and one over 300 says at its
top why it is one module."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("common", "actor", "learner", "human_bridge", "deploy", "benchmarks")  # mapped to khgrl.<folder>
MAX_LINES = 400
REASON_LINES = 300  # above this, the module's docstring says why it is one module: "One module of ~N lines on purpose:"


def _modules(examples: bool = False) -> dict[str, Path]:
    """Every first-party module by its installed name (``khgrl.common.kmp.lcnskmp``) and its file."""
    out = {"khgrl": REPO / "khgrl" / "__init__.py"}
    out.update({f"khgrl.{p.stem}": p for p in (REPO / "khgrl").glob("*.py") if p.stem != "__init__"})
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            if "examples" in path.parts and not examples:
                continue
            rel = path.relative_to(REPO).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out["khgrl." + ".".join(parts)] = path
    return out


def _package(module: str) -> str:
    """The package a module belongs to for the package-level cycle check: ``khgrl.<folder>``, and one level
    deeper inside common/ (``khgrl.common.kmp``, ``khgrl.common.wire``, ...), whose parts are packages of
    their own."""
    parts = module.split(".")
    depth = 3 if parts[1:2] == ["common"] and len(parts) > 3 else 2
    return ".".join(parts[:depth])


def _imports(path: Path, name: str, known: set[str]) -> set[str]:
    """First-party modules that ``name`` imports (at any level of the file: a deferred import still makes
    a cycle for a reader)."""
    tree = ast.parse(path.read_text())
    found = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {name: _imports(path, name, known) for name, path in mods.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if m.startswith(n + ".") or n.startswith(m + "."):
                continue  # a package and its own submodules
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def _package_graph() -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for mod, deps in _graph().items():
        a = _package(mod)
        out.setdefault(a, set()).update(b for b in map(_package, deps) if b != a)
    return out


def test_no_import_cycles_between_packages():
    cycle = _cycle(_package_graph())
    assert cycle is None, "import cycle between packages: " + " -> ".join(cycle)


def test_the_package_cycle_check_finds_a_cycle_of_modules_in_two_packages():
    graph = {"khgrl.deploy.a": {"khgrl.benchmarks.b"}, "khgrl.benchmarks.b": {"khgrl.deploy.c"},
             "khgrl.deploy.c": set()}
    packages: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        packages.setdefault(_package(mod), set()).update(_package(d) for d in deps if _package(d) != _package(mod))
    assert _cycle(graph) is None and _cycle(packages) == ["khgrl.benchmarks", "khgrl.deploy", "khgrl.benchmarks"]


def test_every_package_folder_is_installed():
    """pyproject.toml lists the packages by hand (the folders are mapped into khgrl): a new folder must be listed."""
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {"khgrl"} | {"khgrl." + ".".join(p.parent.relative_to(REPO).parts)
                           for pkg in PACKAGES for p in (REPO / pkg).rglob("__init__.py")}
    assert listed == folders


def test_nothing_imports_the_folders_as_top_level_packages():
    """Every import says ``khgrl.``: from the repository root ``import common`` would work (the folder is on
    sys.path) but not in an installed copy."""
    bad = []
    files = list(_modules(examples=True).values()) + list((REPO / "tests").rglob("*.py"))
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
            bad += [f"{path.relative_to(REPO)}: {n}" for n in names if n.split(".")[0] in PACKAGES]
    assert not bad, bad


def test_no_import_cycles():
    cycle = _cycle(_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_check_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


@pytest.mark.parametrize("name", sorted(_modules()))
def test_module_is_small(name):
    text = _modules()[name].read_text()
    n = len(text.splitlines())
    assert n <= MAX_LINES, f"{name}: {n} lines (at most {MAX_LINES})"
    if n > REASON_LINES:
        doc = ast.get_docstring(ast.parse(text)) or ""
        assert "lines on purpose:" in doc, f"{name}: {n} lines, and its docstring does not say why it is one module"


ROOMS = ("run", "tools", "experiments")  # deploy/'s rooms: each imports only the rooms before it


def test_the_rooms_of_deploy_import_only_the_rooms_before_them():
    """deploy/ is three rooms (a run's life, tools on a finished run, experiments) and ``cli.py`` above them; a
    reader of ``deploy/run/`` needs nothing from the others, a reader of ``tools/`` only ``run/``."""
    room = {name: name.split(".")[2] for name in _modules() if name.count(".") >= 3
            and name.startswith("khgrl.deploy.") and name.split(".")[2] in ROOMS}
    bad = [f"{a} -> {b}" for a, deps in _graph().items() if a in room for b in deps
           if b in room and ROOMS.index(room[b]) > ROOMS.index(room[a])]
    assert set(room.values()) == set(ROOMS) and not bad, bad


def test_test_files_have_unique_names():
    """pytest imports test modules by their base name (rootdir-relative packages are not used here): two
    ``test_x.py`` under tests/unit and tests/integration make collection fail with "import file mismatch"."""
    seen: dict[str, list[str]] = {}
    for path in (REPO / "tests").rglob("test_*.py"):
        seen.setdefault(path.name, []).append(str(path.relative_to(REPO)))
    assert not {name: paths for name, paths in seen.items() if len(paths) > 1}
