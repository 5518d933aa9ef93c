"""The actor's safety settings (``[safety]`` in a run's config file, ``--rate-limit`` and friends on the command line):
what stands between the desired position P_t and the robot (README, "On a real robot").

* **Rate limits** on P_t, per axis, in units of the demonstrations' largest per-step displacement ``d`` (the task's
  own speed scale): a step of P_t is at most ``max_speed`` d, and it changes from one step to the next by at most
  ``max_accel`` d (:class:`~khgrl.common.tasks.safety.RateLimiter`). On in ``--mode robot``, off in simulation
  (the setting of every experiment so far) unless ``--rate-limit on``.
* **Reset phase**: between episodes the robot returns to the start along a rate-limited path (``reset_path``; on in
  robot mode), and with ``confirm_reset`` it holds before each episode until a person says it is ready.
* **Watchdog**: a live human-input client that holds the robot and goes silent for ``human_silence_s`` freezes it at
  its last P_t until the client speaks again or ``correction_timeout`` releases it; a control step that starts more
  than ``deadline_margin`` periods late is counted and reported (the robot held its last P_t meanwhile).
* **Supervision** (``supervision``; on in robot mode): the actor moves the robot only while it hears its supervisor
  (``khgrl up``, or ``khgrl supervise RUN_DIR`` for processes started by hand) every ``heartbeat_s``; after
  ``supervision_timeout`` without a heartbeat it latches the e-stop (:mod:`khgrl.actor.supervision`).
"""

from __future__ import annotations

from dataclasses import dataclass

from khgrl.common.config.fields import ACTOR, _opt

__all__ = ["SafetySettings", "RATE_LIMITS"]

RATE_LIMITS = ("auto", "on", "off")


@dataclass(frozen=True)
class SafetySettings:
    """What the actor does to keep the robot safe (module docstring)."""

    rate_limit: str = _opt("auto", "limit the speed and acceleration of P_t, the position sent to the robot: auto (on "
                                   "in robot mode, off in simulation mode), on or off", RATE_LIMITS, roles=(ACTOR,))
    max_speed: float = _opt(2.0, "with the rate limit: the largest step of P_t per control step on any axis, in units "
                                 "of the demonstrations' largest per-step displacement", roles=(ACTOR,))
    max_accel: float = _opt(0.5, "with the rate limit: the largest change of that step from one control step to the "
                                 "next, in the same units (0: no acceleration limit)", roles=(ACTOR,))
    human_silence_s: float = _opt(0.3, "a live human-input client holding the robot and silent this long freezes it "
                                       "at its last P_t until the client speaks again or correction_timeout releases "
                                       "it (s; 0: off)", roles=(ACTOR,))
    reset_path: str = _opt("auto", "between episodes, drive the robot back to the start (the KMP mean at phase 0) "
                                   "along a path within the rate limits before the next reset: auto (in robot mode), "
                                   "on or off", RATE_LIMITS, roles=(ACTOR,))
    confirm_reset: bool = _opt(False, "before each episode, hold the robot until a person says it is ready (khgrl "
                                      "ready RUN_DIR, or r in a human client's window)", roles=(ACTOR,))
    deadline_margin: float = _opt(1.0, "with --rate: a control step that starts more than this many periods after its "
                                       "deadline is counted as late and reported (the robot held meanwhile)",
                                  roles=(ACTOR,))
    supervision: str = _opt("auto", "hold the robot (the e-stop, latched) unless it hears its supervisor's heartbeat "
                                    "(khgrl up, or khgrl supervise RUN_DIR): auto (on in robot mode), on or off",
                            RATE_LIMITS, roles=(ACTOR,))
    heartbeat_s: float = _opt(0.1, "with supervision: the heartbeat period of khgrl up (and of khgrl supervise "
                                   "RUN_DIR) (s)", roles=())
    supervision_timeout: float = _opt(0.4, "with supervision: seconds without a heartbeat after which the actor "
                                           "latches the e-stop (held within one control period more; released "
                                           "only by khgrl stop --release)", roles=(ACTOR,))

    def supervised(self, mode: str) -> bool:
        """Whether the actor needs its supervisor's heartbeat in ``mode`` (``simulation`` or ``robot``).

        :param mode: the run's mode.
        """
        return self.supervision == "on" or (self.supervision == "auto" and mode == "robot")

    def limits(self, mode: str) -> tuple[float, float] | None:
        """``(max_speed, max_accel)`` when the rate limit is on in ``mode`` (``simulation`` or ``robot``), else None.

        :param mode: the run's mode.
        """
        on = self.rate_limit == "on" or (self.rate_limit == "auto" and mode == "robot")
        return (self.max_speed, self.max_accel) if on else None

    def path(self, mode: str) -> tuple[float, float] | None:
        """The limits of the path back to the start between episodes in ``mode`` (None: no path; the reset alone).

        :param mode: the run's mode.
        """
        on = self.reset_path == "on" or (self.reset_path == "auto" and mode == "robot")
        return (self.max_speed, self.max_accel) if on else None

    def validate(self, correction_timeout: float) -> None:
        if not self.max_speed > 0 or self.max_accel < 0:
            raise ValueError("safety.max_speed must be > 0 and safety.max_accel >= 0")
        if self.human_silence_s < 0 or self.deadline_margin < 0:
            raise ValueError("safety.human_silence_s and safety.deadline_margin must be >= 0")
        if not 0 < self.heartbeat_s < self.supervision_timeout:
            raise ValueError(f"safety.heartbeat_s ({self.heartbeat_s:g} s) must be > 0 and shorter than "
                             f"safety.supervision_timeout ({self.supervision_timeout:g} s)")
        if self.human_silence_s >= correction_timeout > 0:
            raise ValueError(f"safety.human_silence_s ({self.human_silence_s:g} s) must be shorter than "
                             f"correction_timeout ({correction_timeout:g} s), which releases a silent client")
