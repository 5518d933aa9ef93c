"""``--recipe hil-serl`` without processes: HIL-SERL's update schedule (learner/sac_cta.py), its preset
(common/config/hilserl.py), the teacher's successful demonstrations (actor/teach.py), the finishing takeover and
the task-sized safety box."""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.algorithm import algorithm_class
from khgrl.learner.sac_cta import CTASAC, SACCTAAlgorithm
from khgrl.learner.sac_ln import SACLNAlgorithm

from test_sac_ln import _store  # (the same 40 stored rows, a quarter intervened)

SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)


def _trained(cls, settings: TQCSettings, tmp_path) -> dict[str, torch.Tensor]:
    algo = cls.build(None, settings, 5, "cpu")
    algo.set_logger(tmp_path, ("csv",))
    _store(algo)
    algo.train(3, timestep=24, sample_limit=None)
    assert algo.fault() is None
    return algo.model.policy.state_dict()


def test_sac_cta_with_ratio_1_and_backup_entropy_is_sb3s_sac_step_for_step(tmp_path):
    """With cta_ratio 1 and the entropy backup on, sac_cta's step is SB3's SAC.train: the same parameters after 3
    steps as sac_ln's (SB3's own train()), so the replaced train() keeps SAC's order and random draws."""
    assert algorithm_class("sac_cta") is SACCTAAlgorithm
    ours, sb3 = _trained(SACCTAAlgorithm, SMALL, tmp_path / "a"), _trained(SACLNAlgorithm, SMALL, tmp_path / "b")
    assert all(torch.equal(v, sb3[k]) for k, v in ours.items())


def test_sac_cta_updates_the_critics_cta_ratio_times_per_actor_update(tmp_path):
    """cta_ratio 2: per gradient step two critic updates (two minibatches drawn, two target Polyak steps) and one
    actor and temperature update; without the entropy backup the critics learn otherwise than with it."""
    hs = TQCSettings(**{**SMALL.__dict__, "cta_ratio": 2, "backup_entropy": False})
    algo = SACCTAAlgorithm.build(None, hs, 5, "cpu")
    model = algo.model
    assert isinstance(model, CTASAC) and (model.cta_ratio, model.backup_entropy) == (2, False)
    assert not SACCTAAlgorithm.graphs_on(TQCSettings(device="cuda"), "cuda")
    algo.set_logger(tmp_path, ("csv",))
    _store(algo)
    draws, steps = [], {"critic": 0, "actor": 0}
    sample = model.replay_buffer.sample
    model.replay_buffer.sample = lambda *a, **k: draws.append(1) or sample(*a, **k)
    for name in steps:
        opt = getattr(model, name).optimizer
        opt.register_step_post_hook(lambda *_, n=name: steps.__setitem__(n, steps[n] + 1))
    algo.train(3, timestep=24, sample_limit=None)
    assert (len(draws), steps["critic"], steps["actor"]) == (6, 6, 3) and model._n_updates == 3
    assert algo.fault() is None
    on = _trained(SACCTAAlgorithm, TQCSettings(**{**hs.__dict__, "backup_entropy": True}), tmp_path / "c")
    off = _trained(SACCTAAlgorithm, hs, tmp_path / "d")
    assert any(not torch.equal(v, on[k]) for k, v in off.items() if k.startswith("critic."))


def test_cta_ratio_must_be_positive():
    with pytest.raises(ValueError, match="cta_ratio"):
        TQCSettings(cta_ratio=0).validate()


def test_the_recipe_presets_hil_serls_published_settings_unless_given():
    """--recipe hil-serl implies --method hil-serl and HIL-SERL's settings (lr 3e-4, tau 0.005, discount 0.97,
    cta_ratio 2, no backup entropy, 20 demonstrations, the finishing takeover, the task box); a flag given wins;
    the default recipe changes nothing."""
    from khgrl.common.config.hilserl import recipe_runtime
    from khgrl.common.config.settings import RunConfig, resolve

    cfg = resolve(overrides={"recipe": "hil-serl"})
    t = cfg.tqc
    assert (cfg.method, cfg.algo, cfg.takeover) == ("hil-serl", "sac_cta", "finish")
    assert (t.learning_rate, t.tau, t.gamma, t.cta_ratio, t.backup_entropy, t.batch_size, t.sampling) == \
        (3e-4, 0.005, 0.97, 2, False, 256, "rlpd")
    assert (cfg.hilserl.teacher_demos, cfg.hilserl.tries, cfg.hilserl.safety_box) == (20, 60, "task")
    assert resolve(overrides={"recipe": "hil-serl", "tqc": {"gamma": 0.99}}).tqc.gamma == 0.99
    assert resolve(overrides={"method": "hil-serl"}).tqc == resolve(overrides={"method": "hil-serl",
                                                                               "recipe": "none"}).tqc
    assert RunConfig().tqc.cta_ratio == 1 and RunConfig().tqc.backup_entropy and RunConfig().recipe == "none"
    with pytest.raises(ValueError, match="option of method hil-serl"):
        resolve(overrides={"recipe": "hil-serl", "method": "khgrl"})
    cited = recipe_runtime(cfg)["recipe"]
    assert cited["source"].startswith("rail-berkeley/hil-serl@5d02aed")
    assert cited["settings"]["tqc.gamma"] == {"value": 0.97, "source": "examples/experiments/config.py:11, "
                                              "serl_launcher/serl_launcher/utils/launcher.py:84"}
    assert recipe_runtime(RunConfig()) == {}


def test_the_finishing_human_holds_every_step_after_its_first_takeover_in_that_episode_only():
    """--takeover finish: the guide helps at steps 3-5 only; the finishing human holds from step 3 to the
    episode's end (the KMP mean where the guide has nothing), and starts each episode released again. Before:
    the takeover let go after step 5."""
    from khgrl.common.tasks.scripted_human import ScriptedHuman, ScriptedHumanConfig

    def guide(mean, step):
        return mean + 1.0 if 3 <= step <= 5 else None

    def held(finish: bool, episode: int) -> list:
        return [None if p is None else float(p[0]) for p in
                (human.correction(episode, np.array([float(t)]), step=t) for t in range(9))]

    human = ScriptedHuman(guide, ScriptedHumanConfig(episodes=(1, 2), finish=True))
    assert held(True, 1) == [None, None, None, 4.0, 5.0, 6.0, 6.0, 7.0, 8.0]
    assert held(True, 2)[:3] == [None, None, None]
    human = ScriptedHuman(guide, ScriptedHumanConfig(episodes=(1,)))
    assert held(False, 1)[5:] == [6.0, None, None, None]


def test_task_box_is_the_points_bounding_box_plus_margin_inside_the_workspace():
    from khgrl.actor.teach import task_box

    low, high = task_box(np.array([[0.2, 0.5], [0.4, 0.9]]), np.zeros(2), np.ones(2), 0.1)
    np.testing.assert_allclose(low, [0.1, 0.4])
    np.testing.assert_allclose(high, [0.5, 1.0])  # (0.9 + 0.1 clipped to the workspace)


class _Stream:
    def __init__(self) -> None:
        self.count, self.rows, self.cuts = 0, [], 0

    def add(self, *row) -> None:
        self.count += 1
        self.rows.append(row)

    def cut(self) -> None:
        self.cuts += 1


@functools.lru_cache(maxsize=1)
def _world():
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.world import build_task_world

    return build_task_world(load_task("passage:low_cov"))


def _loop(tmp_path, actor: str = "a0", episode: int = 0, **hilserl):
    from khgrl.common.config.settings import resolve
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    cfg = resolve(overrides={"recipe": "hil-serl", "task": "passage:low_cov", "run_dir": str(tmp_path),
                             "hilserl": hilserl})
    (tmp_path / f"actor-{actor}").mkdir(exist_ok=True)
    env = KGRLEnv(world=_world(), seed=0, control="delta")
    return SimpleNamespace(p=SimpleNamespace(env=env, stream=_Stream()), cfg=cfg, id=actor, episode=episode,
                           service=lambda: None, rate_limit=lambda: None, flag=False, teacher=None)


def test_the_teacher_sends_only_successful_demonstrations_in_the_runs_scenes_and_sets_the_task_box(tmp_path):
    """The first actor's teacher records 3 successful passage:low_cov episodes under delta control and sends their
    transitions as intervened (prior) data, each ending in the goal's reward; the delta box shrinks to the task's
    and teacher.json keeps it for a resumed actor. The task's demonstrations are not replayed besides."""
    from khgrl.actor.demos import replays_demos
    from khgrl.actor.teach import TEACHER_FILE, prepare

    loop = _loop(tmp_path, teacher_demos=3)
    workspace = (loop.p.env.delta.low.copy(), loop.p.env.delta.high.copy())
    sent = prepare(loop)
    rows = loop.p.stream.rows
    assert sent == len(rows) > 0 and loop.teacher["kept"] == 3 and loop.teacher["steps"] == sent
    assert all(r[6] is True for r in rows)  # intervened: the learner's prior data
    ends = [r for r in rows if r[4]]  # terminated: the goal reached (passage: success ends the episode)
    assert len(ends) == 3 and all(r[3] > 100 for r in ends)
    box = (loop.p.env.delta.low, loop.p.env.delta.high)
    assert np.all(box[0] >= workspace[0]) and np.all(box[1] <= workspace[1])
    assert np.any(box[0] > workspace[0]) or np.any(box[1] < workspace[1])  # smaller than the workspace
    assert not replays_demos(SimpleNamespace(cfg=loop.cfg, id="a0", episode=0, p=SimpleNamespace(
        stream=SimpleNamespace(count=0))))
    resumed = _loop(tmp_path, episode=4, teacher_demos=3)
    assert prepare(resumed) == 0 and resumed.p.stream.rows == []
    np.testing.assert_allclose(resumed.p.env.delta.low, box[0])
    assert (tmp_path / "actor-a0" / TEACHER_FILE).is_file()
    other = _loop(tmp_path, actor="a1", teacher_demos=1)  # another actor: the box, nothing sent
    assert prepare(other) == 0 and other.p.stream.rows == [] and other.teacher["kept"] == 1


def test_without_a_teacher_the_workspace_box_stays_unless_the_task_box_is_asked_for(tmp_path):
    from khgrl.actor.teach import prepare

    loop = _loop(tmp_path, teacher_demos=0, safety_box="workspace")
    low = loop.p.env.delta.low.copy()
    assert prepare(loop) == 0 and loop.p.stream.rows == []
    np.testing.assert_array_equal(loop.p.env.delta.low, low)
    boxed = _loop(tmp_path, teacher_demos=0, safety_box="task", box_margin=0.0)
    prepare(boxed)
    demos = boxed.p.env.world.demos.reshape(-1, 2)
    np.testing.assert_allclose(boxed.p.env.delta.low, np.maximum(demos.min(axis=0), low))


def test_the_experiment_arm_hil_serl_recipe_runs_khgrl_up_with_the_recipe(tmp_path):
    """``khgrl experiment --methods hil-serl_recipe``: a khgrl up command that resolves to the recipe (HIL-SERL's
    settings, the scripted human finishing its takeovers); its run directory is read back under that method, with
    the demonstrations' steps (``demo_steps``)."""
    import json

    from khgrl.common.config.settings import resolve
    from khgrl.deploy.experiments.experiment import ExperimentConfig, plan_runs, run_argv
    from khgrl.deploy.experiments.run_results import METHOD_LABEL, RUN_NAME, demo_steps
    from khgrl.deploy.run.launcher import build_parser

    cfg = ExperimentConfig(seeds=[0], tasks=["passage:low_cov"], methods=["hil-serl_recipe"], episodes=3)
    (spec,) = plan_runs(cfg)
    argv = run_argv(spec, cfg, tmp_path / spec.name)
    run = resolve(None, build_parser().parse_args(argv[argv.index("up") + 1:]))
    assert (run.method, run.recipe, run.algo, run.takeover, run.tqc.gamma, run.human) == \
        ("hil-serl", "hil-serl", "sac_cta", "finish", 0.97, "scripted")
    assert RUN_NAME.match(spec.name)["method"] == "hil-serl_recipe" and "recipe" in METHOD_LABEL[spec.method]
    (tmp_path / "actor-a0").mkdir()
    assert demo_steps(tmp_path) is None
    (tmp_path / "actor-a0" / "summary.json").write_text(json.dumps({"demo_transitions": 1165}))
    assert demo_steps(tmp_path) == 1165
