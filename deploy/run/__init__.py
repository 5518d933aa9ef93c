"""A run's life: ``khgrl up``'s launcher and what it checks before it starts (``preflight``), the run directory
(``rundir``), the child processes (``supervisor``), the live table (``progress``), how the run ended (``outcome``),
the router, the certificates and Zenoh configurations of ``--secure``, the heartbeat (``supervise``), ``khgrl stop``
/ ``khgrl ready``, ``khgrl keys`` and the live Rerun sink. It imports no other room of ``deploy/``."""
