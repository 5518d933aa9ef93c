"""Fixtures for the math-core tests: the small LC-NS-KMP problems of ``kmp_problems`` (math.md §7)."""

from kmp_problems import box_model, kernel, loose_model, model, ref  # noqa: F401 - pytest fixtures
