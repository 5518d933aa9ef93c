"""Every test under tests/integration/ is an integration test (it starts real processes, windows or whole runs),
marked so whether or not its module says it: ``pytest -m "not integration"`` is then tests/unit/ alone, the fast
part the README promises."""

from __future__ import annotations

from pathlib import Path

import pytest

_HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if _HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.integration)
