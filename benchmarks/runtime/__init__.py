"""Runtime of the distributed system (``khgrl bench runtime``): what the Zenoh split costs and buys.

Every measurement runs real processes (a router, learners, actors: ``khgrl ...`` subprocesses under one
:class:`khgrl.deploy.run.supervisor.ProcessGroup`, stopped at the end) on this machine, in ONE benchmark run, one after
the other, so the ratios are taken under the same load:

1. **ingest** (:mod:`.ingest`): transitions per second a learner (``--learning-starts`` 10^9: it never trains)
   ingests from valid transition batches this process publishes as fast as the acks allow (at most
   ``inflight`` batches beyond the last acknowledged): total transitions / time from the first put to the ack of
   the last seq. Three times: without durability (``--no-journal``, no checkpoints); with the learner's journal,
   timed to the ack that says the last seq durable (its full checkpoints on their schedule, one per replay buffer's
   worth: a buffer of half the stream puts one mid-way); and the old way, ``--no-journal`` with a full checkpoint
   every 2000 transitions.
2. **weights latency** (:mod:`.actor`): an actor (``--rate 50 --max-lead 1000000``, so the lead limit never
   stops it) and a training learner; for every weights version the actor applies: time from the learner's
   publish (the message's ``ts``) to the swap in the actor's control loop (``weights_latency_ms`` of the
   actor's summary).
3. **control-loop period** of that same actor at 50 Hz while the learner trains, next to the gap between
   consecutive ``env.step`` calls of the single-process SB3 baseline (``learner/baseline.py``), which includes
   the 8-gradient-step update every 8 steps.
4. **gradient steps per second** (:mod:`.train`): a learner with a backlog of due training iterations
   (transitions published by this process), from its status messages, next to a standalone TQC (the paper's
   :class:`khgrl.common.config.settings.TQCSettings`, replay buffer of random transitions) timing
   ``model.train(gradient_steps=8, batch_size=256)`` in this process; the two alternate in slices (the learner
   is paused by a control message while this process trains, so they never compete for a core and a drifting
   load hits both alike); the ratio (target >= 100 %). Also reported: the learner's time inside ``train()``
   alone (its ``learner/iteration_s`` scalar), which separates the service loop's overhead from a slower
   ``train()`` in that process.
5. **exactly-once across a learner kill** (:mod:`.resume`; default on unless ``--quick``): an actor streams,
   the learner is SIGKILLed once its journal holds 128 transitions (no full checkpoint yet) and restarted with
   ``--resume``; the final checkpoint's provenance is counted: transitions lost and duplicated.

Numbers on a small shared machine are noisy; the printed note says so and records the load average.
:mod:`.run` runs the stages and :mod:`.table` prints them.
"""

from khgrl.benchmarks.runtime.run import run_runtime_benchmark

__all__ = ["run_runtime_benchmark"]
