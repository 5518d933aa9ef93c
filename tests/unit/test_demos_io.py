"""Demonstration files (common/tasks/demos.py): NPZ and CSV round trips and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from khgrl.common.tasks.demos import DemoFormatError, load_demos, save_demos, validate_demos
from khgrl.common.tasks.passage.scenarios import make_demos

HYP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def random_demos(m: int, n: int, o: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # a wide dynamic range, so the CSV text format is really exercised
    return rng.normal(size=(m, n, o)) * 10.0 ** rng.uniform(-8, 8, size=(m, n, o))


@pytest.mark.parametrize("ext", ["npz", "csv"])
def test_round_trip_scenario_demos(tmp_path, ext):
    demos = make_demos("high_cov")
    path = save_demos(tmp_path / f"d.{ext}", demos)
    assert path.exists() and path.suffix == f".{ext}"
    back = load_demos(path)
    assert back.shape == (9, 400, 2) and back.dtype == np.float64
    if ext == "npz":
        np.testing.assert_array_equal(back, demos)
    else:
        np.testing.assert_allclose(back, demos, rtol=1e-15, atol=0)


@HYP
@given(m=st.integers(1, 5), n=st.integers(2, 30), o=st.integers(1, 4), seed=st.integers(0, 2**16))
def test_round_trip_any_shape(tmp_path, m, n, o, seed):
    demos = random_demos(m, n, o, seed)
    npz = load_demos(save_demos(tmp_path / "x.npz", demos))
    np.testing.assert_array_equal(npz, demos)
    csv = load_demos(save_demos(tmp_path / "x.csv", demos))
    assert csv.shape == (m, n, o)
    np.testing.assert_allclose(csv, demos, rtol=1e-15, atol=0)


def test_save_creates_parent_dirs(tmp_path):
    path = save_demos(tmp_path / "a" / "b" / "d.npz", random_demos(2, 5, 2))
    assert path.is_file()


def test_csv_format_header_and_rows(tmp_path):
    demos = random_demos(2, 3, 2)
    path = save_demos(tmp_path / "d.csv", demos)
    lines = path.read_text().splitlines()
    assert lines[0] == "demo,step,y0,y1"
    assert len(lines) == 1 + 2 * 3
    assert lines[1].startswith("0,0,") and lines[-1].startswith("1,2,")


def test_csv_shuffled_rows_and_comments(tmp_path):
    demos = random_demos(3, 7, 2, seed=4)
    path = save_demos(tmp_path / "d.csv", demos)
    header, *rows = path.read_text().splitlines()
    rng = np.random.default_rng(0)
    rows = [rows[i] for i in rng.permutation(len(rows))]
    shuffled = tmp_path / "shuffled.csv"
    shuffled.write_text(header + "\n" + "\n".join(rows[:5]) + "\n# a comment line\n" + "\n".join(rows[5:]) + "\n")
    np.testing.assert_allclose(load_demos(shuffled), demos, rtol=1e-15, atol=0)


def test_csv_comment_before_header(tmp_path):
    """BUG: the module docstring says lines starting with '#' are comments, but a comment line *before* the
    header (the usual place for one) is taken as the header by np.genfromtxt(names=True): the file fails to
    parse ("got 3 columns instead of 1")."""
    path = tmp_path / "commented.csv"
    path.write_text("# recorded 2024-01-01\ndemo,step,y0\n0,0,1.0\n0,1,2.0\n")
    np.testing.assert_array_equal(load_demos(path), [[[1.0], [2.0]]])


def test_csv_non_contiguous_demo_ids(tmp_path):
    """Demo ids need not be 0..M-1; they are sorted."""
    path = tmp_path / "d.csv"
    path.write_text("demo,step,y0\n7,0,1.5\n7,1,2.5\n3,1,0.5\n3,0,-0.5\n")
    np.testing.assert_array_equal(load_demos(path), [[[-0.5], [0.5]], [[1.5], [2.5]]])


def test_ragged_csv_raises_clear_error(tmp_path):
    path = tmp_path / "ragged.csv"
    path.write_text("demo,step,y0,y1\n0,0,0,0\n0,1,1,1\n0,2,2,2\n1,0,0,0\n1,1,1,1\n")
    with pytest.raises(DemoFormatError, match="ragged") as exc:
        load_demos(path)
    msg = str(exc.value)
    assert "same length" in msg and str(path) in msg
    assert "0: 3" in msg and "1: 2" in msg  # says which demo has how many steps


def test_ragged_array_raises():
    with pytest.raises(DemoFormatError, match="same length"):
        validate_demos([[[0.0, 0.0], [1.0, 1.0]], [[0.0, 0.0]]])


def test_csv_duplicate_or_missing_steps(tmp_path):
    path = tmp_path / "dup.csv"
    path.write_text("demo,step,y0\n0,0,1\n0,0,2\n1,0,1\n1,1,2\n")
    with pytest.raises(DemoFormatError, match="exactly once"):
        load_demos(path)


@pytest.mark.parametrize("ext", ["npz", "csv"])
def test_nan_raises_on_save(tmp_path, ext):
    demos = random_demos(2, 5, 2)
    demos[1, 3, 0] = np.nan
    with pytest.raises(DemoFormatError, match="demo 1, step 3, output 0"):
        save_demos(tmp_path / f"d.{ext}", demos)
    assert not (tmp_path / f"d.{ext}").exists()


def test_nan_raises_on_load_csv(tmp_path):
    path = tmp_path / "nan.csv"
    path.write_text("demo,step,y0,y1\n0,0,0.1,0.2\n0,1,nan,0.3\n")
    with pytest.raises(DemoFormatError, match="non-finite"):
        load_demos(path)


def test_nan_raises_on_load_npz(tmp_path):
    path = tmp_path / "nan.npz"
    np.savez(path, demos=np.array([[[0.0], [np.inf]]]))
    with pytest.raises(DemoFormatError, match="non-finite"):
        load_demos(path)


def test_missing_value_in_csv_raises(tmp_path):
    path = tmp_path / "hole.csv"
    path.write_text("demo,step,y0,y1\n0,0,0.1,\n0,1,0.2,0.3\n")
    with pytest.raises(DemoFormatError):
        load_demos(path)


def test_missing_file_raises(tmp_path):
    with pytest.raises(DemoFormatError, match="no such file"):
        load_demos(tmp_path / "nope.npz")
    assert issubclass(DemoFormatError, ValueError)


@pytest.mark.parametrize("ext", ["txt", "json", "npy"])
def test_wrong_extension_raises(tmp_path, ext):
    path = tmp_path / f"d.{ext}"
    with pytest.raises(DemoFormatError, match="unknown demonstration format"):
        save_demos(path, random_demos(2, 5, 2))
    path.write_text("demo,step,y0\n0,0,1\n0,1,2\n")
    with pytest.raises(DemoFormatError, match="unknown demonstration format"):
        load_demos(path)


def test_npz_without_demos_array(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, trajectories=np.zeros((2, 5, 2)))
    with pytest.raises(DemoFormatError, match="no 'demos' array"):
        load_demos(path)


def test_bad_csv_header(tmp_path):
    path = tmp_path / "h.csv"
    path.write_text("x,y,z\n0,0,1\n")
    with pytest.raises(DemoFormatError, match="header"):
        load_demos(path)


@pytest.mark.parametrize("shape", [(5, 2), (2, 1, 2), (0, 5, 2), (2, 5, 0), (1, 2, 3, 4)])
def test_bad_shapes(shape):
    with pytest.raises(DemoFormatError):
        validate_demos(np.zeros(shape))
