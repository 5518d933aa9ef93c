"""KhGRL: Kernelized human-Guided Reinforcement Learning as separate actor, learner and human-input processes
that exchange transitions, policy weights and human corrections over Eclipse Zenoh.

The installed package is ``khgrl`` alone; the repository's top-level folders are its subpackages
(``actor/`` is :mod:`khgrl.actor`, ``learner/`` is :mod:`khgrl.learner`, and so on; pyproject.toml maps them).
Task authors need only :mod:`khgrl.task`. Importing ``khgrl`` itself loads nothing else, so every process
starts quickly.
"""

__version__ = "0.1.0"

import warnings

# pygame 2.6 looks for its data with pkg_resources when setuptools has it (setuptools < 81, which lerobot-dataset
# pins) and setuptools then warns on stderr that pkg_resources is deprecated: one line of noise before every
# window-less client's one-line error. Only that warning, only from pkg_resources' deprecation, is silenced.
warnings.filterwarnings("ignore", message="pkg_resources is deprecated as an API", category=UserWarning)
