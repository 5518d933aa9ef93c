"""What the actor tells people about itself: per-episode TensorBoard scalars (RUN_DIR/actor-ID/tb), the
status message it publishes about once a second (:class:`~khgrl.common.wire.messages.ActorInfo`), and
``summary.json``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from khgrl.common.delivery.actor_side import RateLimitStats
from khgrl.common.tasks.scene_frame import frame_scene
from khgrl.common.wire.descriptor import MAX_DIM
from khgrl.common.wire.messages import ActorInfo, Frame

__all__ = ["TensorBoard", "RateLimitStats", "status_info", "summary", "frame"]

log = logging.getLogger("khgrl.actor")


class TensorBoard:
    """Per-episode scalars (return, success, intervention statistics, scale). A new writer in an existing
    directory adds an event file next to the earlier ones (a resumed run continues its curves).

    :param log_dir: the tb/ directory; None: write nothing.
    """

    def __init__(self, log_dir: Path | None) -> None:
        self.writer = None
        if log_dir is None:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(log_dir))
        except Exception as exc:  # noqa: BLE001
            log.warning("no TensorBoard scalars: %s", exc)

    def episode(self, st) -> None:
        """Write one finished episode's scalars at step = its episode number.

        :param st: a :class:`~khgrl.common.metrics.EpisodeStats`.
        """
        if self.writer is None:
            return
        iv = st.intervention_steps
        scalars = {
            "episode/return": st.ret, "episode/success": float(st.success), "episode/steps": st.steps,
            "episode/obstacle_steps": st.obstacle_steps,
            "interventions/count": st.interventions, "interventions/steps": iv,
            "interventions/fraction_of_steps": iv / st.steps if st.steps else 0.0,
            "interventions/clipped_fraction": st.clipped_steps / iv if iv else 0.0,
            "interventions/projected_steps": st.projected_steps, "interventions/mean_abs_xi_h": st.mean_abs_xi_h,
        }
        for d, v in enumerate(st.scale_max or []):
            scalars[f"scale/max_L{'xy'[d] if d < 2 else d}"] = v
        try:
            for k, v in scalars.items():
                self.writer.add_scalar(k, float(v), st.episode)
            self.writer.flush()
        except Exception as exc:  # noqa: BLE001 - metrics must never stop the robot
            log.warning("tensorboard write failed (%s): disabled", exc)
            self.writer = None

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def frame(env, actor: str, episode: int, info: dict, t: int, intervening: bool, ret: float, last: bool) -> Frame:
    """The frame the actor publishes after a step. The first frame of an episode (t = 0) of a varying-scene task
    whose KMP was adapted carries the episode's adapted mean, projector and via-points (``scene_*``,
    :func:`~khgrl.common.tasks.scene_frame.frame_scene`); other frames are as before.

    :param env: the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param actor: actor id.
    :param episode: the episode (whole run).
    :param info: the step's info.
    :param t: the step.
    :param intervening: a correction drove the step.
    :param ret: the episode's return so far.
    :param last: the episode's final step.
    """
    return Frame(actor=actor, episode=episode, t=t, phase=float(info["phase"]),
                 robot=np.asarray(env.position, dtype=np.float64), desired=np.asarray(info["desired"], np.float64),
                 mean=np.asarray(env.mapping.mean(t), np.float64), scale=np.asarray(info["scale"], np.float64),
                 intervening=intervening, task=env.task.name, ret=float(ret),
                 next_mean=np.asarray(env.mapping.mean(t + 1), np.float64) if t + 1 < env.horizon else None,
                 last=True if last else None, obs=_frame_obs(getattr(env, "_inner_obs", None)),
                 **frame_scene(env, t, Frame.MAX_BYTES))


def _frame_obs(obs) -> np.ndarray | None:
    """The task environment's observation for a frame: a flat vector of at most 4 * MAX_DIM finite numbers, or None
    (a dict observation, or one too large or not finite, is left out)."""
    try:
        arr = np.asarray(obs, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    return arr if 1 <= arr.size <= 4 * MAX_DIM and np.all(np.isfinite(arr)) else None


def _ms(periods: np.ndarray, q: float) -> float | None:
    return float(np.percentile(periods, q) * 1e3) if periods.size else None


def status_info(*, actor: str, episode: int, t: int, stream, weights, arbiter, rejects, waits: RateLimitStats,
                learner_alive: bool, paused: bool, periods: list[float]) -> ActorInfo:
    """The actor's status (``status/actor/<id>``).

    :param actor: actor id.
    :param episode: current episode (whole run).
    :param t: current step.
    :param stream: the :class:`~khgrl.common.delivery.stream.TransitionStream`.
    :param weights: the :class:`~khgrl.actor.weights.PolicyWeights`.
    :param arbiter: the :class:`~khgrl.actor.arbiter.CorrectionArbiter`.
    :param rejects: the :class:`~khgrl.common.wire.checks.RejectCounter`.
    :param waits: the flow-control waits.
    :param learner_alive: whether a learner is alive.
    :param paused: whether a ``pause`` command holds the actor.
    :param periods: control-loop periods (s); the median of the last 2000 is reported.
    """
    p = np.asarray(periods[-2000:])
    return ActorInfo(
        id=actor, episode=int(episode), t=int(t), transitions=stream.count, sent=stream.sent,
        next_seq=stream.next_seq, outbox=len(stream.outbox), received=stream.received, durable=stream.durable,
        trained=stream.trained, weights_version=weights.version, ack_version=stream.ack_version,
        learner_alive=bool(learner_alive), waits=waits.waits, wait_s=round(waits.wait_s, 3), resends=stream.resends,
        corrections=dict(arbiter.counts), intervening=arbiter.holder is not None, rejects=rejects.by_kind(),
        paused=bool(paused), period_ms_p50=_ms(p, 50))


def summary(*, actor: str, rc: int, stopped_by: str, wall: float, episodes: list, first_episode: int, stream,
            weights, arbiter, rejects, waits: RateLimitStats, max_lead: int, rate: float, periods: list[float],
            scale_updates: int, realtime: bool) -> dict:
    """``RUN_DIR/actor-ID/summary.json`` (this part of the run: a resumed actor reports its new episodes).

    :param actor: actor id.
    :param rc: the exit code.
    :param stopped_by: why it stopped early ('' if it ran to the end).
    :param wall: seconds the run took.
    :param episodes: the episodes finished (EpisodeStats).
    :param first_episode: the number of the first of them (> 1 when resumed; the run has then finished
        ``first_episode - 1 + len(episodes)`` episodes in all).
    :param stream: the :class:`~khgrl.common.delivery.stream.TransitionStream`.
    :param weights: the :class:`~khgrl.actor.weights.PolicyWeights`.
    :param arbiter: the :class:`~khgrl.actor.arbiter.CorrectionArbiter`.
    :param rejects: the :class:`~khgrl.common.wire.checks.RejectCounter`.
    :param waits: the flow-control waits.
    :param max_lead: the flow-control lead.
    :param rate: the control rate (Hz; 0: free-running).
    :param periods: the control-loop periods (s).
    :param scale_updates: refits of the exploration scale.
    :param realtime: whether the control loop ran under SCHED_FIFO.
    """
    p = np.asarray(periods)
    s = stream.summary()
    refused = s.pop("refused_acks")
    stream_id = stream.stream
    out = {"id": actor, "exit_code": rc, "stopped_by": stopped_by or None, "wall_time_s": wall,
           "episodes": len(episodes), "first_episode": first_episode,
           "episodes_in_run": first_episode - 1 + len(episodes), **s,
           "loop_period_ms": {"p50": _ms(p, 50), "p99": _ms(p, 99), "max": float(p.max() * 1e3) if p.size else None,
                              "n": int(p.size), "target": 1e3 / rate if rate > 0 else None},
           "rate_limit": {"waits": waits.waits, "wait_s": waits.wait_s, "max_lead": max_lead},
           **weights.summary(),
           "corrections": dict(arbiter.counts), "scale_updates": scale_updates,
           "successes": int(sum(e.success for e in episodes)), "realtime": realtime,
           "rejects": rejects.by_kind(), "refused_acks": refused, "stream": stream_id}
    return out
