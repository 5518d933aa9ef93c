"""``khgrl eval RUN_DIR``: how well a trained policy does on its own -- deterministic episodes, no human, no
learning.

``RUN_DIR``: any run directory with a learner checkpoint and an actor folder (``khgrl up``'s, or processes started
by hand with one ``--run-dir``), or that actor folder (``RUN_DIR/actor-a0``). The settings (task, ``--demos``,
network) come from ``RUN_DIR/config.json`` (``khgrl up``), else the actor's ``actor-ID/config.json`` (written when
it ends); the policy from the learner's checkpoint; the exploration scale L from the actor's ``scale_model.json``
(KhGRL: the L the policy was trained with; missing, L0 and a warning line). Each episode is reset with ``seed + i``;
the policy acts deterministically (the mean action). Output: a per-episode table and success rate / return mean ±
std on stdout, a CSV (``RUN_DIR/eval/eval.csv`` by default; never overwritten: ``eval-2.csv``, ...), and with
``--gif`` an animation of the first episode (:mod:`khgrl.common.tasks.render`). On a task whose scene does not vary
(no ``Scene``) the output adds that the episodes are one deterministic rollout repeated, not a success rate over
scenes.

``--scenes K`` (:mod:`khgrl.deploy.tools.eval_scenes`): K seeded scenes instead (scene k reset with
``scene_seed(SEED, k, stream="eval")``): the success rate with its 95 % Wilson interval, a per-scene CSV with each
scene's placement (``RUN_DIR/eval/scenes.csv``) and with ``--gif`` the first ``--gif-scenes`` scenes one after
another. A missing or unusable run directory, checkpoint or task is one line and exit 2.

One module of ~320 lines on purpose: the command and its rollouts; its inputs (run directory, checkpoint,
task, scale) are :mod:`~khgrl.deploy.tools.eval_inputs`, the scenes and their CSV
:mod:`~khgrl.deploy.tools.eval_scenes`.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.deploy.run.rundir import still_running
from khgrl.deploy.tools.eval_inputs import (
    EpisodeResult,
    EvalError,
    checkpoint_algo,
    find_model,
    find_run,
    free_path,
    load_policy,
    load_run_task,
    load_scale,
    read_config,
    run_episode,
    trained,
)
from khgrl.deploy.tools.eval_scenes import (
    FIXED_SCENE_NOTE,
    GIF_SCENES_MAX_FRAMES,
    SCENES_CSV,
    scene_caption,
    scene_lines,
    scene_placement,
    write_scenes_csv,
)

__all__ = ["EvalError", "EpisodeResult", "Evaluation", "evaluate", "add_parser", "free_path", "report", "find_run",
           "read_config"]

GIF_MAX_FRAMES = 100  # the first episode is subsampled to about this many frames (~16 kB each)


@dataclass
class Evaluation:
    """What :func:`evaluate` did: the episodes, and where it read and wrote."""

    task: str
    spec: str
    checkpoint: Path
    trained: dict
    scale: str
    episodes: list[EpisodeResult]
    csv: Path | None = None
    gif: Path | None = None
    gif_frames: int = 0
    settings: Path | None = None  # the config.json the run's settings came from
    warning: str = ""  # e.g. a KhGRL run evaluated without its learned scale
    varies: bool = False  # the task's scene varies (it has a Scene)
    seed: int = 0  # the first episode's reset seed; with scenes, S of scene_seed(S, k, "eval")
    scenes: bool = False  # evaluated on seeded scenes (--scenes)
    region: str = ""  # the task's Scene.region
    placements: list[dict] = field(default_factory=list)  # each episode's (scene's) placement
    gif_scenes: int = 1  # scenes the GIF shows
    kmp: str = ""  # whether the KMP was adapted to each scene ("" on a task without via-points)

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else 0.0

    def returns(self) -> np.ndarray:
        return np.array([e.ret for e in self.episodes], dtype=np.float64)


def _write_csv(path: Path, episodes: list[EpisodeResult]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["episode", "seed", "steps", "return", "env_return", "action_cost", "success", "terminated"])
        for e in episodes:
            w.writerow([f"{v:.10g}" if isinstance(v, float) else v for v in asdict(e).values()])


def evaluate(run_dir: str | Path, checkpoint: str | Path | None = None, episodes: int = 10, seed: int | None = None,
             gif: str | Path | None = None, csv_path: str | Path | None = None, actor: str | None = None,
             scenes: int | None = None, gif_scenes: int = 3, adapt: bool | None = None,
             task_spec: str | None = None) -> Evaluation:
    """Evaluate a run's policy (see the module docstring).

    :param run_dir: the run directory (or an actor folder in it: :func:`find_run`).
    :param checkpoint: a checkpoint directory or model.zip (None: the run's learner checkpoint).
    :param episodes: episodes to run (without ``scenes``).
    :param seed: seed of the first episode's reset (episode i: seed + i - 1; None: the run's seed); with ``scenes``
        the seed S of the scenes (scene k: ``scene_seed(S, k, stream="eval")``).
    :param gif: write an animation of the first episode (with ``scenes``: of the first ``gif_scenes``) here.
    :param csv_path: the CSV (None: RUN_DIR/eval/eval.csv, with ``scenes`` RUN_DIR/eval/scenes.csv); an existing
        file is not overwritten.
    :param actor: the actor whose learned exploration scale is used (None: a0, or the actor folder's).
    :param scenes: evaluate on this many seeded scenes (:mod:`khgrl.deploy.tools.eval_scenes`; None: ``episodes``).
    :param gif_scenes: scenes the GIF shows one after another.
    :param adapt: refit the KMP through each scene's via-points at reset (a task with a varying scene and
        via-points; None: as the run did, its ``--adapt/--no-adapt``).
    :param task_spec: evaluate on this task instead of the run's (its spaces must be the run's: e.g.
        ``panda:pick-camera``, ``panda:pick`` with the scene from the camera); None: the run's task.
    :raises EvalError: one line saying what is missing.
    """
    import torch
    from khgrl.common.tasks.api import TaskError
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.common.tasks.world import build_task_world

    if scenes is None and episodes < 1:
        raise EvalError("--episodes must be >= 1")
    if scenes is not None and (scenes < 1 or gif_scenes < 1):
        raise EvalError("--scenes and --gif-scenes must be >= 1")
    run_dir, actor = find_run(run_dir, actor)
    cfg, runtime, settings = read_config(run_dir, actor)
    try:
        model_zip = find_model(run_dir, checkpoint)
    except EvalError:
        if running := still_running(run_dir, "khgrl eval"):  # (a live run: its first checkpoint may still come)
            raise EvalError(f"{running}; it has no checkpoint yet") from None
        raise
    task, spec = load_run_task(cfg, runtime.get("cwd"), task_spec)
    seed = cfg.seed if seed is None else int(seed)
    adapted = bool(cfg.adapt if adapt is None else adapt)
    torch.manual_seed(seed)
    try:
        world = build_task_world(task)
        scale_model, scale_text = load_scale(run_dir, actor, world.out_dim)
        env = KGRLEnv(world=world, seed=seed, scale_model=scale_model, adapt=adapted,
                      control="delta" if cfg.method == "hil-serl" else "kmp",
                      rate_limit=cfg.safety.limits(cfg.stream.mode))  # (the run's: the same dynamics)
    except TaskError as exc:
        raise EvalError(str(exc)) from None
    policy = load_policy(model_zip, env, cfg.tqc, checkpoint_algo(model_zip, cfg))
    result = Evaluation(task=task.name, spec=spec, checkpoint=model_zip.parent, trained=trained(model_zip),
                        scale=scale_text, episodes=[], settings=settings,
                        warning=_scale_warning(cfg, task, scale_model, run_dir / f"actor-{actor}"),
                        varies=task.scene is not None, seed=seed, scenes=scenes is not None,
                        region=task.scene.region if task.scene is not None else "",
                        gif_scenes=min(gif_scenes, scenes) if scenes else 1,
                        kmp=_kmp_text(task, adapted))
    with torch.no_grad():
        recorder = _rollouts(result, env, policy, task, scenes or episodes, gif)
    env.close()
    name = SCENES_CSV if scenes else "eval.csv"
    result.csv = free_path(Path(csv_path) if csv_path else run_dir / "eval" / name)
    if scenes:
        write_scenes_csv(result.csv, result.episodes, result.placements, result.varies)
    else:
        _write_csv(result.csv, result.episodes)
    if recorder is not None:
        result.gif = free_path(Path(gif))
        result.gif_frames = recorder.save(result.gif)
    return result


def _rollouts(result: Evaluation, env: Any, policy: Any, task: Any, count: int, gif: str | Path | None) -> Any:
    """Run the episodes (or scenes) into ``result``; the GIF recorder of the first ``result.gif_scenes`` of them
    (None: no GIF)."""
    from khgrl.common.tasks.scene import scene_seed
    from khgrl.deploy.tools.gif import GifRecorder

    gif_count = result.gif_scenes
    frames = GIF_MAX_FRAMES if not result.scenes else GIF_SCENES_MAX_FRAMES
    recorder = GifRecorder(env, every=-(-env.horizon * gif_count // frames)) if gif else None
    for i in range(count):
        seed = scene_seed(result.seed, i + 1, stream="eval") if result.scenes else result.seed + i
        hook = recorder if recorder is not None and i < gif_count else None
        placed: list[dict] = []

        def on_step(e: Any, done: bool, hook: Any = hook, placed: list = placed, k: int = i + 1) -> None:
            if not placed:  # right after the reset: the scene's placement
                placed.append(scene_placement(task, e) if result.scenes else {})
                if hook is not None:
                    hook.next_episode(scene_caption(k, count, placed[0]) if result.scenes else "")
            if hook is not None:
                hook(e, done)

        result.episodes.append(run_episode(env, policy, i + 1, seed, on_step))
        result.placements.append(placed[0])
    return recorder


def _kmp_text(task: Any, adapted: bool) -> str:
    """How the KMP met each scene, for the report's first line ("" on a task whose scene has no via-points)."""
    if task.scene is None or task.scene.via_points is None:
        return ""
    return "KMP adapted to each scene's via-points" if adapted else "KMP not adapted (--no-adapt)"


def _scale_warning(cfg: Any, task: Any, scale_model: Any, actor_dir: Path) -> str:
    """The line saying a KhGRL run is evaluated without its learned scale (its policy trained under it, III-C)."""
    if cfg.method != "khgrl" or not task.learn_scale or scale_model is not None:
        return ""
    return (f"warning: {actor_dir / 'scale_model.json'} is missing: evaluating with the task's default scale L0, not "
            f"the scale this KhGRL run learned from the human (give the run directory, or the actor folder, of the "
            f"actor whose scale to use: --actor ID)")


# ------------------------------------------------------------------------------------ command
def report(ev: Evaluation) -> str:
    """The text ``khgrl eval`` prints: the inputs, one line per episode, the summary and the files.

    :param ev: the evaluation.
    """
    done = ", ".join(f"{k} {v}" for k, v in ev.trained.items()) or "no state.json"
    source = f"; settings from {ev.settings}" if ev.settings and ev.settings.parent.name.startswith("actor-") else ""
    lines = [ev.warning] if ev.warning else []
    kmp = f"; {ev.kmp}" if ev.kmp else ""
    lines.append(f"task {ev.task} ({ev.spec}){source}; checkpoint {ev.checkpoint} ({done}); scale {ev.scale}{kmp}")
    if ev.scenes:
        lines += scene_lines(ev.episodes, ev.placements, ev.varies, ev.seed, ev.region)
    else:
        lines.append(f"{'episode':>7} {'seed':>6} {'steps':>6} {'return':>10} {'env':>10} {'r_a':>9}  success")
        for e in ev.episodes:
            lines.append(f"{e.episode:>7} {e.seed:>6} {e.steps:>6} {e.ret:>10.2f} {e.env_return:>10.2f} "
                         f"{e.action_cost:>9.2f}  {'yes' if e.success else 'no'}")
        r = ev.returns()
        n_ok = sum(e.success for e in ev.episodes)
        lines.append(f"success {n_ok}/{len(ev.episodes)} ({100 * ev.success_rate:.0f} %); return {r.mean():.2f} ± "
                     f"{r.std():.2f}; steps {np.mean([e.steps for e in ev.episodes]):.1f}")
        lines += [] if ev.varies else [FIXED_SCENE_NOTE]
    lines.append(f"wrote {ev.csv}")
    if ev.gif is not None:
        shown = (f"scenes 1-{ev.gif_scenes}" if ev.gif_scenes > 1 else "scene 1" if ev.scenes else "episode 1")
        lines.append(f"wrote {ev.gif} ({ev.gif_frames} frames of {shown})")
    return "\n".join(lines)


def _cmd_eval(args: argparse.Namespace) -> int:
    if args.gif and "DISPLAY" not in os.environ:
        os.environ.setdefault("MUJOCO_GL", "egl")  # (before MuJoCo is imported) offscreen camera views
    try:
        if args.scenes is not None and args.episodes is not None:
            raise EvalError("give --episodes N (episodes reset with SEED + i) or --scenes K (seeded scenes), not both")
        ev = evaluate(args.run_dir, checkpoint=args.checkpoint, episodes=10 if args.episodes is None else args.episodes,
                      seed=args.seed, gif=args.gif, csv_path=args.csv, actor=args.actor, scenes=args.scenes,
                      gif_scenes=args.gif_scenes, adapt=args.adapt, task_spec=args.task)
    except EvalError as exc:
        print(f"khgrl eval: error: {exc}", file=sys.stderr)
        return 2
    print(report(ev))
    return 0


def at_least_one(text: str) -> int:
    """An argparse type: a count >= 1, refused by the parser before anything loads."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``khgrl eval`` on the subcommands ``sub`` of the ``khgrl`` parser.

    :param sub: the ``add_subparsers()`` object.
    """
    p = sub.add_parser("eval", help="run a trained policy deterministically (no human, no learning): success "
                                    "rate, returns, CSV, GIF")
    p.add_argument("run_dir", metavar="RUN_DIR",
                   help="a run directory with a learner checkpoint and an actor folder (khgrl up's, or processes "
                        "started by hand with one --run-dir), or its actor folder RUN_DIR/actor-ID")
    p.add_argument("--checkpoint", default=None, metavar="PATH",
                   help="a learner checkpoint directory or model.zip (default: RUN_DIR/learner/checkpoint)")
    p.add_argument("--episodes", type=at_least_one, default=None, help="episodes (default: 10)")
    p.add_argument("--scenes", type=at_least_one, default=None, metavar="K",
                   help="instead of --episodes: K seeded scenes, scene k reset with scene_seed(SEED, k, 'eval') "
                        "(the same scenes for every run evaluated with the same SEED); prints the success rate with "
                        "its 95 %% Wilson interval and writes a per-scene CSV with each scene's placement "
                        "(default: none, --episodes)")
    p.add_argument("--seed", type=int, default=None,
                   help="reset seed of the first episode, episode i gets SEED + i - 1; with --scenes the scenes' "
                        "seed (default: the run's seed)")
    p.add_argument("--gif", default=None, metavar="FILE",
                   help="animate episode 1 (with --scenes: the first --gif-scenes scenes) into this GIF "
                        "(default: none)")
    p.add_argument("--gif-scenes", type=at_least_one, default=3, metavar="N",
                   help="with --scenes: scenes the GIF shows one after another (default: %(default)s)")
    p.add_argument("--csv", default=None, metavar="FILE",
                   help="per-episode results (default: RUN_DIR/eval/eval.csv, with --scenes RUN_DIR/eval/scenes.csv; "
                        "never overwritten: eval-2.csv, ...)")
    p.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=None,
                   help="refit the KMP through each scene's via-points at reset, a task whose scene varies "
                        "(--no-adapt: the demonstrations' KMP in every scene; default: as the run did)")
    p.add_argument("--actor", default=None, metavar="ID",
                   help="use the exploration scale this actor learned (default: a0, or the actor folder's)")
    p.add_argument("--task", default=None, metavar="SPEC",
                   help="evaluate on this task instead of the run's, one with the same spaces (e.g. panda:pick-camera "
                        "for a panda:pick run: the scene from the front camera; default: the run's task)")
    p.set_defaults(func=_cmd_eval)
    return p

