"""HIL-SERL's recipe as an option of ``--method hil-serl``: ``--recipe hil-serl`` (default ``none``: the protocol
of docs/results_vs_hilserl.md, the same settings, demonstrations and human for every method).

Sources: rail-berkeley/hil-serl@5d02aed700202c34d120224ae2c8da6795223b0e (``HS``; paths from the repository root).
LeRobot's port (huggingface/lerobot, ``SACConfig`` in src/lerobot/policies/sac/configuration_sac.py) shares the
learning rates (3e-4) and tau (0.005) but defaults to discount 0.99, ``use_backup_entropy`` True and
``utd_ratio`` 1; HIL-SERL's own values are taken here. Each part of the recipe, its setting, and its source:

* **Settings** (:data:`PRESET`, the ``[tqc]`` values ``--recipe hil-serl`` sets unless given):
  learning rate 3e-4 for actor, critics and temperature (HS:serl_launcher/serl_launcher/agents/continuous/
  sac.py:358-366), tau 0.005 (ibid. :369), discount 0.97 (HS:examples/experiments/config.py:11, passed by
  HS:serl_launcher/serl_launcher/utils/launcher.py:58,84), critic updates per actor update ``cta_ratio`` 2
  (HS:examples/experiments/config.py:10; HS:examples/train_rlpd.py:317-338), no entropy term in the critics'
  target (``backup_entropy=False``, HS:serl_launcher/serl_launcher/utils/launcher.py:85), batch 256 of which half
  from the demonstrations (HS:examples/experiments/config.py:9; HS:examples/train_rlpd.py:288-302: RLPD's
  symmetric sampling, ``--sampling rlpd``), replay capacity 200,000 and 100 transitions before training
  (HS:examples/experiments/config.py:14,17), the networks and temperature of ``--algo sac_ln``; the algorithm is
  ``sac_cta`` (:mod:`khgrl.learner.sac_cta`), sac_ln with that update schedule.
* **Successful demonstrations as prior data** (``[hilserl] teacher_demos`` 20, HS:examples/record_demos.py:14
  ``successes_needed`` 20; that script keeps an episode only if it succeeded, :53-57): before the first episode
  the task's scripted teacher -- the scripted human's takeover, holding every step of the episode -- drives the
  robot in the scenes of the run's episodes 1, 2, ... and keeps the episodes that succeed, up to
  ``teacher_demos`` within ``teacher_tries`` (:mod:`khgrl.actor.teach`); they go to the learner as prior
  (intervened) transitions. A LeRobot dataset of demonstrations can be given instead (``--demos lerobot:PATH``;
  it is replayed as today, :mod:`khgrl.actor.demos`).
* **A human who finishes what they take over** (``--takeover finish``): once the scripted human takes the robot
  over in an episode it holds every remaining step, steering to the task's end (HIL-SERL's operator keeps control
  until the episode succeeds, Luo et al. 2024, Section III-B).
* **A task-sized safety box** (``[hilserl] safety_box task``): the delta actions' box is the bounding box of the
  teacher's successful demonstrations (or, without them, the task's), widened by ``box_margin`` of the workspace's
  extent on each side and kept in the workspace (HIL-SERL bounds the pose a few centimetres around the task:
  HS:examples/experiments/ram_insertion/config.py:42-43 ``ABS_POSE_LIMIT_LOW``/``HIGH``).
* **Learned gripper**: not here. On Fetch and Panda the gripper closes on the tasks' phase schedule, for every
  method alike (HIL-SERL's ``setup_mode`` "single-arm-fixed-gripper" is its default, HS:examples/experiments/
  config.py:36-38, the pre-grasped case).
"""

from __future__ import annotations

from dataclasses import dataclass

from khgrl.common.config.fields import ACTOR, _opt

__all__ = ["HilSerlSettings", "RECIPES", "SAFETY_BOXES", "PRESET", "SOURCE", "SOURCES", "recipe_runtime"]

RECIPES = ("none", "hil-serl")
SAFETY_BOXES = ("workspace", "task")
SOURCE = "rail-berkeley/hil-serl@5d02aed700202c34d120224ae2c8da6795223b0e"
# what --recipe hil-serl sets unless the run gives it (the module docstring says where each value comes from)
PRESET = {"method": "hil-serl", "algo": "sac_cta", "takeover": "finish",
          "tqc": {"learning_rate": 3e-4, "tau": 0.005, "gamma": 0.97, "cta_ratio": 2, "backup_entropy": False,
                  "batch_size": 256, "buffer_size": 200_000, "learning_starts": 100, "sampling": "rlpd"},
          "hilserl": {"teacher_demos": 20, "safety_box": "task"}}

_SAC, _CFG = "serl_launcher/serl_launcher/agents/continuous/sac.py", "examples/experiments/config.py"
_LAUNCH = "serl_launcher/serl_launcher/utils/launcher.py"
# each preset setting -> where in SOURCE it comes from (written into the run's config.json, runtime.recipe)
SOURCES = {"tqc.learning_rate": f"{_SAC}:358-366", "tqc.tau": f"{_SAC}:369", "tqc.gamma": f"{_CFG}:11, {_LAUNCH}:84",
           "tqc.cta_ratio": f"{_CFG}:10, examples/train_rlpd.py:317-338", "tqc.backup_entropy": f"{_LAUNCH}:85",
           "tqc.batch_size": f"{_CFG}:9", "tqc.buffer_size": f"{_CFG}:14", "tqc.learning_starts": f"{_CFG}:17",
           "tqc.sampling": "examples/train_rlpd.py:288-302", "algo": f"{_LAUNCH}:50-92 (make_sac_pixel_agent)",
           "takeover": "Luo et al. 2024, Section III-B", "hilserl.teacher_demos": "examples/record_demos.py:14,53-57",
           "hilserl.safety_box": "examples/experiments/ram_insertion/config.py:42-43"}


def recipe_runtime(cfg) -> dict:
    """What ``khgrl up`` adds to the run's ``config.json`` runtime for a recipe: the recipe, its source, and each
    preset setting with the value the run uses and where it comes from (empty for ``--recipe none``).

    :param cfg: the run's :class:`~khgrl.common.config.settings.RunConfig`
    """
    if cfg.recipe == "none":
        return {}
    settings = {}
    for key, where in SOURCES.items():
        table, _, name = key.rpartition(".")
        value = getattr(getattr(cfg, table) if table else cfg, name)
        settings[key] = {"value": value, "source": where}
    return {"recipe": {"name": cfg.recipe, "source": SOURCE, "settings": settings,
                       "doc": "common/config/hilserl.py"}}


@dataclass(frozen=True)
class HilSerlSettings:
    """The ``[hilserl]`` table: the parts of HIL-SERL's recipe that are not learner settings (module docstring)."""

    teacher_demos: int = _opt(0, "--method hil-serl: before the first episode the task's scripted teacher records "
                                 "this many successful demonstrations in the run's scenes as prior data (HIL-SERL: "
                                 "20; 0: none, the task's demonstrations are replayed as today)", roles=(ACTOR,))
    teacher_tries: int = _opt(0, "episodes the teacher may try to record them in (0: 3 x teacher_demos)",
                              roles=(ACTOR,))
    safety_box: str = _opt("workspace", "--method hil-serl: the box the delta actions are clipped to: the task's "
                                        "workspace, or the task: the demonstrations' bounding box +- box_margin",
                           SAFETY_BOXES, roles=(ACTOR,))
    box_margin: float = _opt(0.1, "with safety_box task: the margin on each side, as a fraction of the workspace's "
                                  "extent on that axis", roles=(ACTOR,))

    @property
    def tries(self) -> int:
        """Episodes the teacher may use: ``teacher_tries``, or 3 x ``teacher_demos``."""
        return self.teacher_tries or 3 * self.teacher_demos

    def validate(self) -> None:
        if self.teacher_demos < 0 or self.teacher_tries < 0 or not 0 <= self.box_margin <= 1:
            raise ValueError("hilserl.teacher_demos and teacher_tries must be >= 0 and box_margin in [0, 1]")
        if self.teacher_tries and self.teacher_tries < self.teacher_demos:
            raise ValueError("hilserl.teacher_tries must be at least teacher_demos")
