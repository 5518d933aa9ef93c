"""A content-addressed cache of fitted GMMs, so that a process that fits the same demonstrations again (every start
of ``khgrl up``'s launcher, its actors, ``khgrl eval``) reads the fit instead of importing scikit-learn (~1.5 s) and
running EM again.

The key is a SHA-256 of everything the fit depends on: the demonstrations' float64 bytes and shape, the number of
components, the seed, ``reg_covar``, and the versions of scikit-learn and numpy. A hit returns exactly the arrays
the fit returned when it was stored (``weights_``, ``means_``, ``covariances_``, float64), so a seeded run gives the
same episodes with or without the cache. Files are ``gmm-<key>.npz`` in ``$KHGRL_CACHE_DIR`` (default
``$XDG_CACHE_HOME/khgrl``, else ``~/.cache/khgrl``); ``KHGRL_CACHE_DIR=off`` turns the cache off. They are written
atomically (a temporary file, then a rename), read with ``allow_pickle=False``, and a file that does not read as
three arrays of the expected shapes is ignored (the fit runs again and replaces it). Nothing else is ever deleted.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

__all__ = ["FittedGMM", "cache_dir", "gmm_key", "load_gmm", "store_gmm"]

OFF = "off"


@dataclass(frozen=True)
class FittedGMM:
    """The parameters of a fitted full-covariance GMM (as scikit-learn's ``GaussianMixture`` names them)."""

    weights_: np.ndarray  # (C,)
    means_: np.ndarray  # (C, D)
    covariances_: np.ndarray  # (C, D, D)


def cache_dir() -> Path | None:
    """Where fitted GMMs are kept; None when ``KHGRL_CACHE_DIR=off``."""
    given = os.environ.get("KHGRL_CACHE_DIR")
    if given is not None:
        return None if given.strip().lower() in (OFF, "") else Path(given)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "khgrl"


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "none"


def gmm_key(data: np.ndarray, n_components: int, seed: int, reg_covar: float) -> str:
    """The cache key of fitting ``data`` (the joint points, (P, D) float64) with these settings.

    :param data: the points the GMM is fitted on.
    :param n_components: C.
    :param seed: the fit's random state.
    :param reg_covar: the fit's covariance regularisation.
    """
    data = np.ascontiguousarray(data, dtype=np.float64)
    h = hashlib.sha256()
    h.update(repr((data.shape, int(n_components), int(seed), float(reg_covar), _version("scikit-learn"),
                   np.__version__)).encode())
    h.update(data.tobytes())
    return h.hexdigest()


def load_gmm(key: str, n_components: int, dim: int) -> FittedGMM | None:
    """The cached fit of ``key``, or None (not there, the cache off, or a file that does not read as one).

    :param key: from :func:`gmm_key`.
    :param n_components: C, to check the arrays' shapes.
    :param dim: D, the joint points' dimension.
    """
    where = cache_dir()
    if where is None:
        return None
    try:
        with np.load(where / f"gmm-{key}.npz", allow_pickle=False) as f:
            fit = FittedGMM(*(np.asarray(f[k], np.float64) for k in ("weights", "means", "covariances")))
    except (OSError, ValueError, KeyError):
        return None
    shapes = (fit.weights_.shape, fit.means_.shape, fit.covariances_.shape)
    if shapes != ((n_components,), (n_components, dim), (n_components, dim, dim)):
        return None
    if not all(np.all(np.isfinite(a)) for a in (fit.weights_, fit.means_, fit.covariances_)):
        return None
    return fit


def store_gmm(key: str, fit: FittedGMM) -> None:
    """Keep ``fit`` under ``key`` (best effort: a read-only or full disk only means no cache).

    :param key: from :func:`gmm_key`.
    :param fit: the fitted parameters.
    """
    where = cache_dir()
    if where is None:
        return
    tmp = None
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".gmm-{key}.", suffix=".npz", dir=where)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, weights=fit.weights_, means=fit.means_, covariances=fit.covariances_)
        os.replace(tmp, where / f"gmm-{key}.npz")
    except OSError:
        if tmp is not None:  # (only the temporary file this call made; a cache that cannot be written is skipped)
            with contextlib.suppress(OSError):
                Path(tmp).unlink(missing_ok=True)
