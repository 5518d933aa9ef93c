"""The public API for task authors (README, "Bring your own task"): everything a task module imports.

``from khgrl.task import Task, View, Cuboid, Sphere, Point, KMPConfig, save_demos, load_demos, Scene, ViaPoint``

* :class:`Task` -- a task: environment factory, demonstrations, workspace, constraints, KMP settings, view;
* :class:`View` and the shapes it draws: :class:`Cuboid` (an axis-aligned box; named so that it does not clash
  with ``gymnasium.spaces.Box``), :class:`Sphere`, :class:`Point`;
* :class:`KMPConfig` -- the GMM/GMR and LC-NS-KMP settings;
* :func:`save_demos` / :func:`load_demos` -- demonstrations (M, N, O) as ``.npz`` or ``.csv``;
* :class:`Scene`, :class:`ViaPoint`, :func:`scene_seed` -- a scene that changes every episode and the via-points
  that adapt the KMP to it;
* :class:`TaskError` -- what a task that cannot run raises; :func:`load_task` -- a task from its spec.
"""

from khgrl.common.kmp.fit import KMPConfig
from khgrl.common.tasks.api import Cuboid, Point, Sphere, Task, TaskError, View, load_task
from khgrl.common.tasks.demos import load_demos, save_demos
from khgrl.common.tasks.scene import Scene, ViaPoint, scene_seed

__all__ = ["Task", "View", "Cuboid", "Sphere", "Point", "KMPConfig", "save_demos", "load_demos", "TaskError",
           "load_task", "Scene", "ViaPoint", "scene_seed"]
