"""RUN_DIR/actor-ID/steps/episode-N.npz: what a real KGRLEnv episode records, read back; listeners; bad files."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.step_records import STEP_FIELDS, StepRecord, read_steps
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.kgrl_env import KGRLEnv


class _Listener:
    def __init__(self):
        self.calls = []

    def start(self, episode, scene):
        self.calls.append(("start", episode, sorted(scene)))

    def step(self, episode, row):
        self.calls.append(("step", episode, row["t"]))

    def finish(self, episode, arrays, stats):
        self.calls.append(("finish", episode, len(arrays["t"]), stats))


def _episode(env, rec, episode, correct_at=()):
    obs, _ = env.reset_episode(episode)
    rec.start(episode, env)
    done, rng = False, np.random.default_rng(episode)
    while not done:
        p_h = env.mapping.mean(env.t) + 0.01 if env.t in correct_at else None
        env.set_correction(p_h)
        action = rng.uniform(-1, 1, env.action_space.shape)
        nxt, r, term, trunc, info = env.step(action)
        rec.step(obs, info, env, r, term, trunc, p_h, False)
        obs, done = nxt, term or trunc
    return rec.finish(obs, "stats")


def test_round_trip_of_real_episodes(tmp_path):
    env = KGRLEnv(load_task("passage:low_cov"), seed=0)
    lis = _Listener()
    rec = StepRecord(tmp_path, listeners=(lis,))
    p1 = _episode(env, rec, 1, correct_at={3, 4, 5})
    p2 = _episode(env, rec, 2)
    assert p1.name == "episode-000001.npz" and p2.exists() and rec.written == 2
    assert not list((tmp_path / "steps").glob("*.tmp*"))
    eps = read_steps(tmp_path)
    assert [int(e["episode"]) for e in eps] == [1, 2]
    e = eps[0]
    n = len(e["t"])
    assert list(e["t"]) == list(range(n))
    assert e["intervened"][[3, 4, 5]].all() and not e["intervened"][6:].any()
    assert np.isfinite(e["p_h"][[3, 4, 5]]).all() and np.isnan(e["p_h"][~e["intervened"]]).all()
    np.testing.assert_allclose(e["p_h"][3], env.mapping.model.grid_mean[3] + 0.01)  # the P_h applied
    assert e["obs"].dtype == np.float32 and e["obs"].shape[0] == n and e["final_obs"].shape == e["obs"].shape[1:]
    assert e["kmp_mean"].shape == (env.horizon, 2) and e["kmp_projector"].shape == (env.horizon, 2, 2)
    assert e["terminated"][-1] or e["truncated"][-1]
    kinds = [c[0] for c in lis.calls]
    assert kinds[0] == "start" and kinds.count("finish") == 2 and kinds.count("step") == n + len(eps[1]["t"])
    assert lis.calls[-1] == ("finish", 2, len(eps[1]["t"]), "stats")


def test_listeners_only_and_nothing(tmp_path):
    env = KGRLEnv(load_task("passage:low_cov"), seed=0)
    lis = _Listener()
    assert _episode(env, StepRecord(None, listeners=(lis,)), 1) is None and lis.calls[-1][0] == "finish"
    off = StepRecord(None)
    assert not off.active and _episode(env, off, 1) is None


def test_bad_files_are_refused(tmp_path):
    d = tmp_path / "steps"
    d.mkdir()
    np.savez(d / "episode-000001.npz", t=np.arange(3))
    with pytest.raises(ValueError, match="missing"):
        read_steps(tmp_path)
    fields = {k: np.zeros(3) for k in (*STEP_FIELDS, "final_obs", "kmp_mean", "kmp_projector", "via", "episode")}
    fields["reward"] = np.zeros(2)
    np.savez(d / "episode-000001.npz", **fields)
    with pytest.raises(ValueError, match="length"):
        read_steps(tmp_path)
    (d / "episode-000001.npz").unlink()
    (d / "notes.txt").write_text("x")
    assert read_steps(tmp_path) == [] and read_steps(tmp_path / "none") == []


def test_image_keys_come_from_the_first_step_file_without_reading_its_arrays(tmp_path):
    from khgrl.common.step_records import image_keys, steps_dir

    assert image_keys(tmp_path / "actor-a0") == ()
    d = steps_dir(tmp_path / "actor-a0")
    d.mkdir(parents=True)
    np.savez(d / "episode-000002.npz", t=np.arange(2))
    np.savez(d / "episode-000001.npz", t=np.arange(2), **{"image/cam": np.zeros((2, 4, 4, 3), np.uint8),
                                                         "image/pixels/wrist": np.zeros((2, 4, 4, 3), np.uint8)})
    assert sorted(image_keys(tmp_path / "actor-a0")) == ["cam", "pixels/wrist"]  # episode 1's, the first
