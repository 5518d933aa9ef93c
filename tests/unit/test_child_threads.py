"""Children of the process supervisor get one BLAS/OpenMP thread unless the caller says otherwise."""

from __future__ import annotations

import os
import sys

from khgrl.deploy.run.supervisor import ONE_THREAD, ProcessGroup

PRINT = "import os; print(' '.join(os.environ.get(v, '-') for v in %r))" % (ONE_THREAD,)


def _child_env(tmp_path, env: dict) -> list[str]:
    with ProcessGroup(tmp_path / "logs", env=env) as group:
        p = group.start("probe", [sys.executable, "-c", PRINT])
        assert group.wait_all(30, [p]) and p.poll() == 0
    return (tmp_path / "logs" / "probe.log").read_text().split()


def test_one_thread_by_default_and_the_callers_setting_wins(tmp_path):
    base = {k: v for k, v in os.environ.items() if k not in ONE_THREAD}
    assert _child_env(tmp_path / "a", base) == ["1"] * len(ONE_THREAD)
    assert _child_env(tmp_path / "b", {**base, "OMP_NUM_THREADS": "4"})[0] == "4"
