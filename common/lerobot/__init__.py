"""LeRobot datasets (format v3.0), read and written with LeRobot's own dataset library (the ``lerobot`` extra):
``library.py`` (the one import of it), ``demos.py`` (``--demos lerobot:PATH``: episodes -> M x N x O
demonstrations), ``writer.py`` (frames -> a dataset folder, all or nothing). ``khgrl export`` is
``deploy/tools/export.py``.
"""
