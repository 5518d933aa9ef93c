"""Two evaluations on the same scenes: McNemar's exact p, the discordant scenes, the placements' distance."""

from __future__ import annotations

import csv
import math

import pytest
from khgrl.deploy.experiments.paired import compare_pair, main, mcnemar_exact


def _csv(path, successes, xs, seeds=None):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scene", "seed", "varies", "cube_x", "cube_y", "success", "return", "env_return", "action_cost",
                    "steps", "terminated"])
        for i, (s, x) in enumerate(zip(successes, xs)):
            w.writerow([i + 1, (seeds or range(100, 200))[i], True, x, 0.0, s, 1.0, 1.0, 0.0, 43, s])
    return path


def test_mcnemar_exact_is_the_binomial_test_of_the_discordant_pairs() -> None:
    assert mcnemar_exact(0, 0) == 1.0 and mcnemar_exact(3, 3) == 1.0
    assert mcnemar_exact(0, 6) == pytest.approx(2 / 64)  # all six discordant pairs one way
    assert mcnemar_exact(1, 9) == pytest.approx(2 * (1 + 10) / 2 ** 10)
    assert mcnemar_exact(9, 1) == mcnemar_exact(1, 9)
    assert mcnemar_exact(2, 7) == pytest.approx(2 * sum(math.comb(9, k) for k in range(3)) / 2 ** 9)


def test_a_pair_of_the_same_scenes(tmp_path) -> None:
    a = _csv(tmp_path / "true.csv", [True, True, True, False], [0.5, 0.6, 0.4, 0.45])
    b = _csv(tmp_path / "cam.csv", [True, False, True, True], [0.503, 0.6, 0.396, 0.45])
    out = compare_pair(a, b)
    assert (out["a_successes"], out["b_successes"], out["only_a"], out["only_b"]) == (3, 3, 1, 1)
    assert out["placement"] == ["cube_x", "cube_y"]
    assert out["distance"]["max"] == pytest.approx(0.004) and out["distance"]["per_scene"][1] == 0.0


def test_other_scenes_are_refused(tmp_path, capsys) -> None:
    a = _csv(tmp_path / "a.csv", [True], [0.5])
    b = _csv(tmp_path / "b.csv", [True], [0.5], seeds=[7])
    with pytest.raises(ValueError, match="not of the same scenes"):
        compare_pair(a, b)
    assert main(["--a", str(a), "--b", str(b)]) == 2 and "one --seed" in capsys.readouterr().err
