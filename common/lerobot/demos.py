"""Demonstrations from a LeRobot dataset: ``--demos lerobot:PATH[?feature=NAME&dims=A:B&n=N]``.

* ``PATH``: a local LeRobot dataset folder (format v3.0, as LeRobot's writer makes it), read with LeRobot's own
  loader, offline.
* ``feature``: the feature that is the position, a numeric vector per frame (default ``observation.state``);
  ``dims=A:B``: its entries A..B-1 (Python's slice; default: all). The width taken must equal the task's O.
* **One episode = one demonstration**, resampled to N grid points by linear interpolation over the episode's
  normalised phase: frame k of an episode of F frames (in ``frame_index`` order) is at u_k = k / (F - 1), grid
  point j at s_j = j / (N - 1), and each output is interpolated linearly in u (first and last frame kept exactly).
  N is ``n=`` if given, else the task's own demonstrations' N, else the longest episode's frame count.
* Refused, naming the episode: one of fewer than 2 frames, or a non-finite value (its frame and entry).

The M x N x O array then goes the way of a ``.npz`` demonstration file (``khgrl up`` keeps it as
``RUN_DIR/demos.npz``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from khgrl.common.lerobot.library import STATE, LeRobotMissing, NotADataset, open_dataset

__all__ = ["PREFIX", "LeRobotDemoError", "DemoSpec", "is_lerobot_spec", "parse_spec", "resample",
           "load_lerobot_demos"]

PREFIX = "lerobot:"
_KEYS = ("feature", "dims", "n")


class LeRobotDemoError(ValueError):
    """A ``lerobot:`` demonstration source that cannot be used (named, with the reason)."""


@dataclass(frozen=True)
class DemoSpec:
    """A parsed ``lerobot:PATH?...``.

    :param path: the dataset folder.
    :param feature: the feature read as the position.
    :param dims: (start, stop) of the slice of it taken, None: all of it.
    :param n: grid points per demonstration, None: the caller's choice.
    """

    path: Path
    feature: str = STATE
    dims: tuple[int | None, int | None] | None = None
    n: int | None = None

    def text(self) -> str:
        """The spec written back (``lerobot:PATH?feature=...``)."""
        query = [f"feature={self.feature}"]
        if self.dims is not None:
            query.append("dims=" + ":".join("" if d is None else str(d) for d in self.dims))
        if self.n is not None:
            query.append(f"n={self.n}")
        return f"{PREFIX}{self.path}?{'&'.join(query)}"


def is_lerobot_spec(value) -> bool:
    """Whether a ``--demos`` value names a LeRobot dataset (``lerobot:...``)."""
    return isinstance(value, str) and value.startswith(PREFIX)


def _dims(text: str, spec: str) -> tuple[int | None, int | None]:
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return (int(start) if start.strip() else None, int(stop) if stop.strip() else None)
    except ValueError:
        raise LeRobotDemoError(f"--demos {spec}: dims={text!r} is not a slice START:STOP (e.g. dims=0:3)") from None


def parse_spec(spec: str, resolve: bool = False) -> DemoSpec:
    """Parse ``lerobot:PATH[?feature=NAME&dims=A:B&n=N]``.

    :param spec: the ``--demos`` value.
    :param resolve: make PATH absolute (``khgrl up`` passes the spec on to processes elsewhere).
    :raises LeRobotDemoError: not a ``lerobot:`` spec, an unknown key or a bad value.
    """
    if not is_lerobot_spec(spec):
        raise LeRobotDemoError(f"--demos {spec}: not a LeRobot source (lerobot:PATH[?feature=NAME&dims=A:B&n=N])")
    rest = spec[len(PREFIX):]
    path, sep, query = rest.rpartition("?")
    if not sep or "=" not in query:
        path, query = rest, ""
    if not path:
        raise LeRobotDemoError(f"--demos {spec}: no dataset folder after {PREFIX!r}")
    fields: dict[str, str] = {}
    for item in filter(None, query.split("&")):
        key, _, value = item.partition("=")
        if key not in _KEYS:
            raise LeRobotDemoError(f"--demos {spec}: unknown key {key!r} (known: {', '.join(_KEYS)})")
        fields[key] = value
    n = fields.get("n")
    if n is not None and not (n.isdigit() and int(n) >= 2):
        raise LeRobotDemoError(f"--demos {spec}: n={n!r} must be an integer >= 2")
    folder = Path(path).expanduser()
    return DemoSpec(path=folder.resolve() if resolve else folder, feature=fields.get("feature") or STATE,
                    dims=_dims(fields["dims"], spec) if "dims" in fields else None,
                    n=int(n) if n is not None else None)


def resample(points: np.ndarray, n: int) -> np.ndarray:
    """(F, W) frames -> (n, W): linear interpolation over the normalised phase, frame k at k / (F - 1), output j
    at j / (n - 1).

    :param points: one episode's values, F >= 2 frames in order.
    :param n: grid points.
    """
    points = np.asarray(points, dtype=np.float64)
    u = np.linspace(0.0, 1.0, len(points))
    s = np.linspace(0.0, 1.0, n)
    return np.stack([np.interp(s, u, points[:, w]) for w in range(points.shape[1])], axis=1)


def _feature_columns(spec: DemoSpec, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values (F, W) float64, episode_index (F,), frame_index (F,)) of the whole dataset."""
    try:
        ds = open_dataset(spec.path)
    except (NotADataset, LeRobotMissing) as exc:
        raise LeRobotDemoError(f"--demos {source}: {exc}") from None
    features = ds.meta.features
    ft = features.get(spec.feature)
    numeric = [k for k, f in features.items() if f["dtype"] not in ("image", "video", "string")]
    if ft is None:
        raise LeRobotDemoError(f"--demos {source}: the dataset has no feature {spec.feature!r}; its numeric "
                               f"features: {', '.join(numeric)}")
    if spec.feature not in numeric or len(ft["shape"]) != 1:
        raise LeRobotDemoError(f"--demos {source}: feature {spec.feature!r} is {ft['dtype']} of shape "
                               f"{tuple(ft['shape'])}, not a numeric vector per frame")
    data = ds.hf_dataset.with_format("numpy")
    values = np.asarray(data[spec.feature], dtype=np.float64).reshape(len(data), -1)
    return values, np.asarray(data["episode_index"]), np.asarray(data["frame_index"])


def _select(values: np.ndarray, spec: DemoSpec, source: str, o: int | None) -> np.ndarray:
    width = values.shape[1]
    start, stop = spec.dims if spec.dims is not None else (None, None)
    idx = range(width)[slice(start, stop)]
    if spec.dims is not None and (len(idx) == 0 or (stop or 0) > width or (start or 0) >= width):
        raise LeRobotDemoError(f"--demos {source}: dims={start}:{stop} is outside feature {spec.feature!r} of "
                               f"width {width}")
    if o is not None and len(idx) != o:
        raise LeRobotDemoError(f"--demos {source}: feature {spec.feature!r} gives {len(idx)} values per frame"
                               f"{'' if spec.dims is None else ' (dims ' + str(start) + ':' + str(stop) + ')'}, the "
                               f"task's positions have O = {o}: choose dims=A:B of width {o}")
    return values[:, list(idx)]


def _episodes(values: np.ndarray, episode: np.ndarray, frame: np.ndarray, source: str) -> list[np.ndarray]:
    out = []
    for ep in np.unique(episode):
        rows = np.flatnonzero(episode == ep)
        points = values[rows[np.argsort(frame[rows], kind="stable")]]
        if len(points) < 2:
            raise LeRobotDemoError(f"--demos {source}: episode {int(ep)} has {len(points)} frame(s); a "
                                   f"demonstration needs at least 2")
        bad = np.argwhere(~np.isfinite(points))
        if len(bad):
            k, w = bad[0]
            raise LeRobotDemoError(f"--demos {source}: episode {int(ep)}, frame {int(k)}, entry {int(w)} of the "
                                   f"selected feature is not finite ({points[k, w]})")
        out.append(points)
    if not out:
        raise LeRobotDemoError(f"--demos {source}: the dataset has no episodes")
    return out


def load_lerobot_demos(spec: str, n: int | None = None, o: int | None = None) -> np.ndarray:
    """The demonstrations of a ``lerobot:`` source as float64 (M, N, O): one per episode, resampled.

    :param spec: ``lerobot:PATH[?feature=NAME&dims=A:B&n=N]``.
    :param n: grid points per demonstration when the spec has no ``n=`` (None: the longest episode's frames).
    :param o: the width the task needs (None: any).
    :raises LeRobotDemoError: naming what is wrong (the folder, the feature, its width, an episode).
    """
    return _load(spec, n, o).copy()


@lru_cache(maxsize=4)
def _load(spec: str, n: int | None, o: int | None) -> np.ndarray:
    parsed = parse_spec(spec)
    values, episode, frame = _feature_columns(parsed, spec)
    episodes = _episodes(_select(values, parsed, spec, o), episode, frame, spec)
    grid = parsed.n or n or max(len(e) for e in episodes)
    out = np.stack([resample(e, grid) for e in episodes])
    out.setflags(write=False)
    return out
