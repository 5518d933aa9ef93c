"""Confidence intervals of a success rate: the Wilson score interval (``khgrl eval --scenes``, ``khgrl report``).

Wilson (1927), "Probable inference, the law of succession, and statistical inference", JASA 22: the set of p whose
score test of k successes in n trials does not reject at the level given. Unlike the normal-approximation (Wald)
interval it stays inside [0, 1] and is not empty at 0/n or n/n (Newcombe 1998 recommends it for small n).
"""

from __future__ import annotations

import math
from statistics import NormalDist

__all__ = ["wilson_interval", "rate_text"]


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """(low, high) of the Wilson score interval of ``successes`` out of ``n``:
    (p + z^2/(2n) -+ z sqrt(p (1 - p) / n + z^2 / (4 n^2))) / (1 + z^2 / n), p = successes / n, z the normal
    quantile of 1 - (1 - confidence) / 2.

    :param successes: k, 0 <= k <= n.
    :param n: trials, n >= 1.
    :param confidence: the interval's coverage (0.95: a 95 % interval).
    :raises ValueError: n < 1, k outside [0, n] or a confidence outside (0, 1).
    """
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes}/{n}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    z = NormalDist().inv_cdf(1.0 - (1.0 - confidence) / 2.0)
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    low = 0.0 if successes == 0 else max(0.0, centre - half)  # exact ends at 0/n and n/n (no rounding residue)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


def rate_text(successes: int, n: int, confidence: float = 0.95) -> str:
    """``37/50 = 74 % (95 % CI 60-84 %, Wilson)``: the rate and its Wilson interval in whole percent.

    :param successes: k.
    :param n: trials.
    :param confidence: the interval's coverage.
    """
    low, high = wilson_interval(successes, n, confidence)
    return (f"{successes}/{n} = {100 * successes / n:.0f} % ({100 * confidence:g} % CI {100 * low:.0f}-"
            f"{100 * high:.0f} %, Wilson)")
