"""Run the suite's files longest first, from the seconds each took in a measured run (``file_seconds.json``).

pytest-xdist's ``--dist loadfile`` hands a worker one file at a time, in collection order (``--no-loadscope-reorder``
in pyproject.toml keeps that order; its default sorts files by their number of tests, which put the long integration
files, with one or two tests each, last). Handing the longest out first and the short unit files last is the
longest-processing-time rule: the workers finish within about one short file of each other.

A file with no recorded time counts as ``_UNKNOWN_S`` under tests/integration/ (a new integration test starts real
processes) and 0 s elsewhere. ``pytest --file-seconds-out PATH`` writes this run's seconds per file (setup, call and
teardown of every test summed) for the next run to use.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import pytest

_RECORD = Path(__file__).with_name("file_seconds.json")
_UNKNOWN_S = 30.0


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--file-seconds-out", default=None, metavar="PATH",
                     help="write the seconds each test file took in this run, as JSON (default: not written)")


def _file(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


def _recorded() -> dict[str, float]:
    try:
        return {str(k): float(v) for k, v in json.loads(_RECORD.read_text()).items()}
    except (OSError, ValueError, AttributeError):
        return {}


def expected_seconds(path: str, recorded: dict[str, float]) -> float:
    """How long a test file is expected to take.

    :param path: the file, relative to the repository (as in a test's node id)
    :param recorded: seconds per file from a measured run
    :return: the recorded seconds, else ``_UNKNOWN_S`` for an integration file and 0 for any other
    """
    if path in recorded:
        return recorded[path]
    return _UNKNOWN_S if path.startswith("tests/integration/") else 0.0


def longest_first(nodeids: list[str], recorded: dict[str, float]) -> list[int]:
    """The order that runs whole files longest first, keeping the tests of a file in their own order.

    :param nodeids: the collected tests' node ids, in collection order
    :param recorded: seconds per file from a measured run
    :return: the indices of ``nodeids`` in the new order
    """
    first_seen: dict[str, int] = {}
    for nodeid in nodeids:
        first_seen.setdefault(_file(nodeid), len(first_seen))
    rank = {f: (-expected_seconds(f, recorded), i) for f, i in first_seen.items()}
    return sorted(range(len(nodeids)), key=lambda i: (rank[_file(nodeids[i])], i))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    order = longest_first([item.nodeid for item in items], _recorded())
    items[:] = [items[i] for i in order]


class _Recorder:
    def __init__(self, out: Path) -> None:
        self.out = out
        self.seconds: dict[str, float] = defaultdict(float)

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        self.seconds[_file(report.nodeid)] += report.duration

    def pytest_sessionfinish(self) -> None:
        ranked = dict(sorted(((f, round(s, 1)) for f, s in self.seconds.items()), key=lambda kv: -kv[1]))
        self.out.write_text(json.dumps(ranked, indent=1) + "\n")


def pytest_configure(config: pytest.Config) -> None:
    out = config.getoption("--file-seconds-out")
    if out and not hasattr(config, "workerinput"):  # the controller sees every worker's reports
        config.pluginmanager.register(_Recorder(Path(out)), "file_seconds_recorder")
