"""Grids of runs and what is learnt from them: ``khgrl experiment`` (locally or on Ray's workers), the runs' results
and learning criteria, ``khgrl report`` with its statistics, figures and tables. Of the other rooms of ``deploy/`` it
imports :mod:`khgrl.deploy.run` and :mod:`khgrl.deploy.tools` (an evaluation's scenes)."""
