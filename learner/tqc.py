"""``--algo tqc`` (the default): sb3-contrib's TQC with the paper's settings (Section IV; the run's ``[tqc]``
settings, :class:`~khgrl.common.config.settings.TQCSettings`), and sb3-contrib's defaults for the rest
(2 critics of 25 quantiles each, the top 2 of each dropped from the target)."""

from __future__ import annotations

from khgrl.learner.sb3_offpolicy import SB3OffPolicy

__all__ = ["TQCAlgorithm"]


class TQCAlgorithm(SB3OffPolicy):
    """sb3-contrib TQC through the learner-algorithm interface (:class:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy`)."""

    name = "tqc"

    @classmethod
    def sb3_class(cls) -> type:
        from sb3_contrib import TQC

        return TQC

    @classmethod
    def policy_class(cls) -> type:
        from sb3_contrib.tqc.policies import TQCPolicy

        return TQCPolicy
