"""The layout map (docs/layout.md, the whole map, and the README's "Layout" section) is checked against the code:
every module path it names exists, and every function, class or method it names (``file.py`` ``Class.method``, or
a bare name after a file) is defined in the file named before it. A renamed or removed function makes this fail,
so the map cannot rot."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SPAN = re.compile(r"`([^`]+)`")
PATH = re.compile(r"^[\w./-]+\.py$")
NAME = re.compile(r"^\.?[A-Za-z_]\w*(\.[A-Za-z_]\w*)?$")
NOT_A_NAME = re.compile(r"(^khgrl\b)|(\.(csv|json|toml|md|png|gif|npz|rrd|msgpack)$)")  # modules, file names


def layout_section(text: str) -> str:
    """The text from a ``## Layout`` (or ``# Layout``) heading to the next heading of that level."""
    level = "\n## " if "\n## Layout\n" in text else "\n# "
    start = text.index(f"{level}Layout\n")
    end = text.find(level, start + 1)
    return text[start:end if end > 0 else None]


def definitions(path: Path) -> set[str]:
    """``f``, ``Class``, ``Class.method`` and ``CONSTANT`` for every top-level function, class, method and
    assignment in a module."""
    out: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            out |= {t.id for t in targets if isinstance(t, ast.Name)}
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out.add(node.name)
        elif isinstance(node, ast.ClassDef):
            out.add(node.name)
            methods = [m for m in node.body if isinstance(m, (ast.FunctionDef, ast.AsyncFunctionDef))]
            out |= {f"{node.name}.{m.name}" for m in methods}
    return out


def check_layout(text: str, repo: Path = REPO) -> list[str]:
    """Every problem with the Layout section's names, one line each (empty when all resolve).

    Table rows start with a folder (``actor/``): a path in that row is relative to it (else to the repository
    root). Outside tables a path is relative to the repository root. A name span after a path refers to that file;
    ``.cut`` refers to the class named last in it.
    """
    problems: list[str] = []
    for line in layout_section(text).splitlines():
        spans = SPAN.findall(line)
        folder = spans[0] if line.startswith("| `") and spans and spans[0].endswith("/") else ""
        current: Path | None = None
        cls = ""
        for span in spans:
            span = span.strip()
            if PATH.match(span):
                rel = folder + span if (repo / folder / span).is_file() or "/" not in span else span
                current, cls = repo / rel, ""
                if not current.is_file():
                    problems.append(f"no file {rel}")
                    current = None
            elif current is not None and NAME.match(span) and not NOT_A_NAME.search(span):
                name = cls + span if span.startswith(".") else span
                if name not in definitions(current):
                    problems.append(f"{current.relative_to(repo)} defines no {name}")
                cls = name.split(".")[0] if name[:1].isupper() else cls
    return problems


def test_every_path_and_function_the_layout_names_exists():
    for page in ("README.md", "docs/layout.md"):
        problems = check_layout("\n" + (REPO / page).read_text())
        assert not problems, f"{page}: Layout is out of date:\n" + "\n".join(problems)


def test_the_check_finds_a_missing_file_and_a_missing_method(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "mod.py").write_text("class Loop:\n    def step(self):\n        pass\n\ndef run():\n    pass\n")
    good = "x\n## Layout\n\n1. `pkg/mod.py` `Loop.step` → `.step` → `run`\n| `pkg/` | `mod.py` (the loop) |\n## Next\n"
    assert check_layout(good, tmp_path) == []
    bad = ("x\n## Layout\n\n`pkg/mod.py` `Loop.drain` → `gone` (`out.csv`, `khgrl.task`); `pkg/other.py`\n"
           "| `pkg/` | `nope.py` |\n")
    assert check_layout(bad, tmp_path) == ["pkg/mod.py defines no Loop.drain", "pkg/mod.py defines no gone",
                                           "no file pkg/other.py", "no file pkg/nope.py"]
