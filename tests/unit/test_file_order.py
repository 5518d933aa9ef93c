"""The suite's order: whole files, longest first (tests/file_order.py)."""

from file_order import expected_seconds, longest_first


def test_files_run_longest_first_and_keep_their_own_order() -> None:
    ids = ["tests/unit/test_a.py::t1", "tests/integration/test_b.py::t1", "tests/unit/test_a.py::t2",
           "tests/integration/test_c.py::t1", "tests/integration/test_c.py::t2", "tests/integration/test_new.py::t"]
    recorded = {"tests/integration/test_b.py": 12.0, "tests/integration/test_c.py": 90.0, "tests/unit/test_a.py": 1.0}
    order = [ids[i] for i in longest_first(ids, recorded)]
    assert order == ["tests/integration/test_c.py::t1", "tests/integration/test_c.py::t2",
                     "tests/integration/test_new.py::t", "tests/integration/test_b.py::t1",
                     "tests/unit/test_a.py::t1", "tests/unit/test_a.py::t2"]


def test_an_unrecorded_file_counts_as_an_integration_test_only_under_integration() -> None:
    assert expected_seconds("tests/integration/test_new.py", {}) == 30.0
    assert expected_seconds("tests/unit/test_new.py", {}) == 0.0
    assert expected_seconds("tests/unit/test_new.py", {"tests/unit/test_new.py": 4.5}) == 4.5
