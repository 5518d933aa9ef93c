"""Tools on a finished run, each of which refuses a live one: ``khgrl eval`` (``evaluate``, ``eval_inputs``,
``eval_scenes``, ``gif``, and the Wilson ``intervals`` that ``khgrl report`` shares), ``khgrl export`` and
``khgrl view``. Of the other rooms of ``deploy/`` it imports only :mod:`khgrl.deploy.run` (the run directory)."""
