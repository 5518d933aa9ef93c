"""The delivery layer: everything between a process's loop and the Zenoh network.

Transport (:mod:`~khgrl.common.delivery.transport`, :mod:`~khgrl.common.delivery.declare`,
:mod:`~khgrl.common.delivery.zenoh_config`, :mod:`~khgrl.common.delivery.acl`); the sender side of the actor's
transition stream (:mod:`~khgrl.common.delivery.stream`, :mod:`~khgrl.common.delivery.outbox`,
:mod:`~khgrl.common.delivery.restart`, the window and flow control in :mod:`~khgrl.common.delivery.actor_side`, the
checks on what the actor receives in :mod:`~khgrl.common.delivery.trust` and :mod:`~khgrl.common.delivery.senders`);
the receiver side at the learner (:mod:`~khgrl.common.delivery.ingest`: fair inbox, per-actor ordering;
:mod:`~khgrl.common.delivery.learner_side`: decoding, acks, the ingest thread); and each role's declarations
(:mod:`~khgrl.common.delivery.actor_link`, :mod:`~khgrl.common.delivery.learner_link`,
:mod:`~khgrl.common.delivery.task_link`).
"""

# The only first-party modules that import ``zenoh`` (paths from the repository root). Everything else reaches
# Zenoh through this package's functions and classes; tests/unit/test_delivery_layer.py checks it, the README lists it.
ZENOH_MODULES = (
    "common/delivery/transport.py",  # sessions, the inbox and ring buffers
    "common/delivery/declare.py",  # publishers, subscribers, queryables, tokens, queries, with QoS in words
    "common/delivery/zenoh_config.py",  # the configuration a process connects with
    "deploy/run/router.py",  # the router process (reads its access-control setting)
    "deploy/examples/drag_client.py",  # a third-party client, written as a user would: Zenoh directly
)
