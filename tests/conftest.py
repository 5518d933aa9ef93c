"""Every test process computes with one OpenMP / torch thread, as KhGRL's own processes do (actor/main.py, and
learner/main.py with ``--learner-threads 1``): under pytest-xdist on a 2-core machine a second intra-op thread per
worker oversubscribes the cores, and OpenMP's spin-waits made the backward pass of an 8x8 network 15x slower
(test_shares' lock-step test: 36.5 s with torch's default threads, 11.8 s with one, on the same loaded machine).
Set before torch is imported; the processes a test starts inherit it."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
