"""The actor's exploration scale L (KhGRL): refit it from each human intervention, publish it, and keep its
history (``scale.npz``, the data of the paper's Fig. 6) and its model (``scale_model.json``, so that a
resumed actor continues with the scale it had learned)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Callable

import numpy as np
from khgrl.common.kmp.scale import ScaleModel
from khgrl.common.wire.messages import Scale

__all__ = ["ExplorationScale"]

log = logging.getLogger("khgrl.actor")


class ExplorationScale:
    """Learns L from interventions (KhGRL on scenarios with a learned scale; otherwise L stays constant).

    :param env: the task's KGRL environment (its ``mapping`` holds the scale model).
    :param actor: this actor's id.
    :param khgrl: whether the method uses human corrections (KGRL publishes and learns nothing).
    :param publish: sends a :class:`~khgrl.common.wire.messages.Scale` message.
    """

    def __init__(self, env, actor: str, khgrl: bool, publish: Callable[[Scale], None]) -> None:
        self.env = env
        self.actor = actor
        self.khgrl = khgrl
        self.learns = khgrl and env.task.learn_scale
        self.publish_fn = publish
        self.updates = 0
        self.history: list[tuple[int, np.ndarray]] = []  # (episode, L table over the grid) after each refit

    def publish(self) -> None:
        """Publish the current model (and its table over the grid) -- KhGRL only."""
        if not self.khgrl:
            return
        m = self.env.mapping
        table = m.scale_table
        self.publish_fn(Scale(actor=self.actor, model=m.scale_model.to_dict(),
                              table=None if table is None else np.asarray(table, dtype=np.float64)))

    def refit(self, segment: list[tuple], episode: int) -> None:
        """Refit L from one intervention: its (xi_h, phase) per step.

        :param segment: the intervention's steps (empty: nothing to do).
        :param episode: the episode it happened in (for the history).
        """
        if not segment or not self.learns:
            return
        xi = np.array([s[0] for s in segment])
        ph = np.array([s[1] for s in segment])
        self.env.mapping.update_scale(xi, ph)
        self.updates += 1
        if self.env.mapping.scale_table is not None:
            self.history.append((episode, np.array(self.env.mapping.scale_table, dtype=np.float64)))
        self.publish()

    def save(self, out_dir: Path) -> None:
        """``scale.npz``: L over the grid's phases as it ended (``table``, (N, O); KGRL and scenarios without a
        learned scale keep the constant default) and after each refit (``history``, with the ``episodes``
        whose intervention produced it); ``scale_model.json``: the model itself.

        :param out_dir: RUN_DIR/actor-ID.
        """
        m = self.env.mapping
        (Path(out_dir) / "scale_model.json").write_text(json.dumps(m.scale_model.to_dict()))
        if m.scale_table is None:  # a position-input scale model has no table over phase
            return
        table = np.asarray(m.scale_table, dtype=np.float64)
        hist = np.array([h for _, h in self.history]) if self.history else np.zeros((0, *table.shape))
        np.savez(Path(out_dir) / "scale.npz", table=table, phases=np.asarray(m.phases),
                 history=hist, episodes=np.array([e for e, _ in self.history], dtype=np.int64))

    def restore(self, out_dir: Path) -> None:
        """Continue from what an earlier part of the run saved (``--resume``): its model and history.

        :param out_dir: RUN_DIR/actor-ID.
        """
        path = Path(out_dir) / "scale_model.json"
        if self.learns and path.is_file():
            self.env.mapping.scale_model = ScaleModel.from_dict(json.loads(path.read_text()))
            self.env.mapping.refresh_scale()
            log.info("resumed the exploration scale model (%d updates)", self.env.mapping.scale_model.n_updates)
        npz = Path(out_dir) / "scale.npz"
        if npz.is_file():
            with np.load(npz) as data:
                self.history = [(int(e), np.asarray(h)) for e, h in zip(data["episodes"], data["history"])]
