"""Camera frames on the wire (common/wire/frames.py, batch.py): a camera batch round-trips through encode/decode
against the receiver's Dims; each malformed field is refused with a ProtocolError naming it; the size limit grows
with the cameras (a vector batch's is unchanged); the run key's mac covers the frames."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from khgrl.common.delivery import run_key
from khgrl.common.wire.base import Dims
from khgrl.common.wire.batch import MAX_BATCH, Transitions
from khgrl.common.wire.checks import ProtocolError, pack_array
from khgrl.common.wire.frames import MAX_FRAME_BYTES, PREV, max_rows, pack_frames
from khgrl.common.wire.protocol import decode, encode

SHAPE = (8, 6, 3)
CAMS = (("cam", SHAPE), ("wrist", (4, 4, 1)))
DIMS = Dims(obs=3, out=2, cameras=CAMS)


def _batch(n: int = 6, ends: tuple[int, ...] = (2,), seed: int = 0) -> Transitions:
    """n rows of one stream, episodes ending at rows ``ends``, frames packed as an actor packs them."""
    rng = np.random.default_rng(seed)
    done = np.zeros(n, bool)
    done[list(ends)] = True
    shapes = dict(CAMS)
    stream = {k: rng.integers(0, 256, (n + 1, *s), dtype=np.uint8) for k, s in shapes.items()}
    obs = {k: v[:-1].copy() for k, v in stream.items()}
    nxt = {k: v[1:].copy() for k, v in stream.items()}
    for r in np.flatnonzero(done[:-1]):  # the next row starts a new episode: its own first frame
        for k in obs:
            obs[k][r + 1] = rng.integers(0, 256, shapes[k], dtype=np.uint8)
    frames, of, nf = pack_frames(obs, nxt, done, list(shapes), continues=False)
    f32 = np.float32
    return Transitions(actor="a0", first_step=10, obs=rng.random((n, 3), dtype=f32), next_obs=rng.random((n, 3),
                       dtype=f32), action=rng.uniform(-1, 1, (n, 2)).astype(f32), reward=np.ones(n, f32),
                       terminated=done.astype(np.uint8), truncated=np.zeros(n, np.uint8),
                       intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), task="abcd", frames=frames,
                       obs_frame=of.astype(np.int32), next_frame=nf.astype(np.int32))


def _wire(msg: Transitions) -> dict:
    return msgpack.unpackb(encode(msg, "a0", 3), raw=False)


def _decode(m: dict, dims: Dims = DIMS) -> Transitions:
    return decode(Transitions, msgpack.packb(m, use_bin_type=True), dims)


def test_round_trip() -> None:
    msg = _batch()
    got = decode(Transitions, encode(msg, "a0", 3), DIMS)
    assert set(got.frames) == {"cam", "wrist"} and len(got.frames["cam"]) == 6 + 1 + 1  # n + 1 episode start + 1
    for k in got.frames:
        assert np.array_equal(got.frames[k], msg.frames[k])
    assert np.array_equal(got.obs_frame, msg.obs_frame) and np.array_equal(got.next_frame, msg.next_frame)
    assert got.obs_frame.dtype == np.int32 and got.obs_frame[0] == 0  # row 0's frame sent, not PREV
    assert np.array_equal(got.obs, msg.obs)  # the state vectors stay obs/next_obs
    any_dims = decode(Transitions, encode(msg, "a0", 3))  # (a receiver that knows no task: consistent is enough)
    assert set(any_dims.frames) == {"cam", "wrist"}


def test_vector_batch_unchanged() -> None:
    msg = _batch()
    vector = msg.replace(frames=None, obs_frame=None, next_frame=None)
    got = decode(Transitions, encode(vector, "a0", 3), Dims(obs=3, out=2, cameras=()))
    assert got.frames is None and got.obs_frame is None
    assert Transitions.limit(Dims(obs=3, out=2, cameras=())) == Transitions.MAX_BYTES == vector.max_bytes()
    with pytest.raises(ProtocolError, match="frames: a batch of a task without cameras"):
        decode(Transitions, encode(msg, "a0", 3), Dims(obs=3, out=2, cameras=()))


def test_size_limit_grows_with_the_cameras() -> None:
    big = (("front", (256, 256, 4)), ("wrist", (256, 256, 4)))
    assert Transitions.limit(Dims(cameras=big)) <= Transitions.MAX_BYTES + MAX_FRAME_BYTES
    small = Transitions.limit(DIMS) - Transitions.MAX_BYTES
    assert small == (8 * 6 * 3 + 16) * 2 * MAX_BATCH  # two frames per row of the largest batch
    rows = max_rows(big, MAX_BATCH)
    assert 2 * rows * 2 * 256 * 256 * 4 <= MAX_FRAME_BYTES < 2 * (rows + 1) * 2 * 256 * 256 * 4


def _set(m: dict, field: str, value) -> dict:
    m = dict(m)
    m[field] = value
    return m


def _bad_cases() -> list:
    m = _wire(_batch())
    of, nf = np.frombuffer(m["obs_frame"]["data"], np.int32), np.frombuffer(m["next_frame"]["data"], np.int32)
    cam = np.frombuffer(m["frames"]["cam"]["data"], np.uint8).reshape(-1, *SHAPE)

    def idx(arr, r, v, dtype=np.int32):
        a = arr.astype(dtype)
        a[r] = v
        return pack_array(a)

    frames = dict(m["frames"])
    return [
        (_set(m, "frames", None), "frames: missing"),
        (_set(m, "obs_frame", None), "obs_frame: missing"),
        (_set(m, "frames", {"cam": m["frames"]["cam"]}), "frames: cameras"),
        (_set(m, "frames", {**frames, "cam": pack_array(cam.astype(np.float32))}), "frames[cam]: dtype"),
        (_set(m, "frames", {**frames, "cam": pack_array(cam[:, :4])}), "frames[cam]: expected shape"),
        (_set(m, "frames", {**frames, "cam": pack_array(cam[:-1])}), "frames: the cameras hold different"),
        (_set(m, "obs_frame", pack_array(of.astype(np.int64))), "obs_frame: dtype"),
        (_set(m, "next_frame", pack_array(nf[:-1])), "next_frame: expected shape"),
        (_set(m, "next_frame", idx(nf, 5, 99)), "next_frame[5]: 99 outside"),
        (_set(m, "obs_frame", idx(of, 2, PREV)), "obs_frame[2]: -1 outside"),
        (_set(m, "next_frame", idx(nf, 0, PREV)), "next_frame[0]: -1 outside"),
        (_set(m, "obs_frame", idx(of, 2, 0)), "obs_frame[2]: 0, but row 1 did not end"),
    ]


@pytest.mark.parametrize("case", range(12))
def test_malformed_frames_refused(case: int) -> None:
    m, words = _bad_cases()[case]
    with pytest.raises(ProtocolError) as err:
        _decode(m)
    assert words in str(err.value), str(err.value)


def test_too_many_frames_refused() -> None:
    msg = _batch(n=4, ends=())  # no episode starts: at most 4 + 0 + 1 frames
    extra = {k: np.concatenate([v, v[:1]]) for k, v in msg.frames.items()}
    with pytest.raises(ProtocolError, match=r"frames: 6 frames for 4 rows and 0 episode starts, 1..5 allowed"):
        _decode(_wire(msg.replace(frames=extra)))


def test_prev_allowed_at_row_0_and_after_an_episode_end_any_frame() -> None:
    msg = _batch(n=5, ends=(1,))
    of = msg.obs_frame.copy()
    of[0] = PREV
    assert decode(Transitions, encode(msg.replace(obs_frame=of), "a0", 3), DIMS).obs_frame[0] == PREV


def test_mac_covers_the_frames() -> None:
    key = b"k" * 32
    msg = run_key.sign_batch(_batch(), key, 3)
    assert run_key.mac_of(decode(Transitions, encode(msg, "a0", 3), DIMS), key) == msg.mac
    m = _wire(msg)
    assert run_key.wire_batch_mac(m, key) == msg.mac
    cam = np.frombuffer(m["frames"]["cam"]["data"], np.uint8).copy()
    cam[0] ^= 1
    m["frames"] = {**m["frames"], "cam": {**m["frames"]["cam"], "data": cam.tobytes()}}
    tampered = _decode(m)
    assert run_key.mac_of(tampered, key) != msg.mac and run_key.wire_batch_mac(m, key) != msg.mac
    vector = run_key.sign_batch(msg.replace(frames=None, obs_frame=None, next_frame=None, mac=None), key, 3)
    assert vector.mac != msg.mac
