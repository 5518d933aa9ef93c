"""The wire protocol's validator: valid messages round-trip, every kind of bad message is rejected with a
reason (never an unexpected exception)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from common.protocol import MAX_BYTES, SCHEMA_VERSION, Keys, ProtocolError, RejectCounter, decode, encode, pack_array


def _batch(n=4, **over):
    rng = np.random.default_rng(0)
    fields = dict(
        actor="a0",
        first_step=0,
        obs=rng.uniform(size=(n, 5)).astype(np.float32),
        next_obs=rng.uniform(size=(n, 5)).astype(np.float32),
        action=rng.uniform(-1, 1, size=(n, 2)).astype(np.float32),
        reward=rng.normal(size=n).astype(np.float32),
        terminated=np.zeros(n, np.uint8),
        truncated=np.zeros(n, np.uint8),
        intervened=np.array([1, 0, 0, 1][:n] + [0] * max(0, n - 4), np.uint8),
        clipped=np.zeros(n, np.uint8),
    )
    fields.update(over)
    return encode("transitions", "a0", 3, **fields)


def _raw(kind="correction", **over):
    msg = {"v": SCHEMA_VERSION, "kind": kind, "sender": "pad", "seq": 0, "ts": 1.0, "client": "pad", "actor": "a0",
           "active": True, "p_h": [0.5, 0.5]}
    msg.update(over)
    return msgpack.packb({k: v for k, v in msg.items() if v is not ...}, use_bin_type=True)


def test_transitions_round_trip():
    msg = decode("transitions", _batch())
    assert msg["seq"] == 3 and msg["actor"] == "a0"
    assert msg["obs"].shape == (4, 5) and msg["obs"].dtype == np.float32
    np.testing.assert_array_equal(msg["intervened"], [1, 0, 0, 1])


def test_correction_round_trip_and_release():
    msg = decode("correction", encode("correction", "pad", 0, client="pad", actor="a0", active=True, p_h=[0.2, 0.7]))
    np.testing.assert_allclose(msg["p_h"], [0.2, 0.7])
    rel = decode("correction", encode("correction", "pad", 1, client="pad", actor="a0", active=False))
    assert rel["p_h"] is None
    addressed = decode("correction", encode("correction", "pad", 2, client="pad", actor="a0", active=False,
                                            episode=4, step=17))
    assert addressed["step"] == 17 and addressed["episode"] == 4 and addressed["p_h"] is None


def test_frame_next_mean_is_optional_and_checked():
    base = dict(actor="a0", episode=1, t=3, phase=0.1, robot=[0.1, 0.2], desired=[0.1, 0.2], mean=[0.1, 0.2],
                scale=[20.0, 20.0], intervening=False, scenario="high_cov")
    assert "next_mean" not in decode("frame", encode("frame", "a0", 0, **base))
    np.testing.assert_allclose(decode("frame", encode("frame", "a0", 1, next_mean=[0.3, 0.4], **base))["next_mean"],
                               [0.3, 0.4])
    with pytest.raises(ProtocolError, match="next_mean"):
        decode("frame", encode("frame", "a0", 2, next_mean=[0.3, float("nan")], **base))


def test_weights_round_trip():
    tensors = {"latent_pi.0.weight": np.ones((256, 5), np.float32), "mu.bias": np.zeros(2, np.float32)}
    msg = decode("weights", encode("weights", "learner", 0, version=7, trained={"a0": 104}, tensors=tensors))
    assert msg["version"] == 7 and msg["tensors"]["latent_pi.0.weight"].shape == (256, 5)


@pytest.mark.parametrize(
    "payload,reason",
    [
        (b"", "not msgpack"),
        (b"\xc1\xff\x00garbage", "not msgpack"),
        (msgpack.packb([1, 2, 3]), "not a map"),
        (_raw(v=0), "schema version"),
        (_raw(v=SCHEMA_VERSION + 1), "schema version"),
        (_raw(kind="frame"), "kind"),
        (_raw(sender="a/b"), "bad identifier"),
        (_raw(sender=""), "bad identifier"),
        (_raw(seq=-1), "seq"),
        (_raw(seq="3"), "seq"),
        (_raw(active="yes"), "active"),
        (_raw(p_h=[0.5]), "p_h"),
        (_raw(p_h=[0.5, float("nan")]), "not finite"),
        (_raw(p_h=[0.5, float("inf")]), "not finite"),
        (_raw(p_h=["a", 0.5]), "p_h"),
        (_raw(actor=...), "actor"),
        (_raw(step=3), "needs its episode"),
        (_raw(step=-1, episode=1), "step"),
        (_raw(step=1.5, episode=1), "step"),
        (b"\x00" * (MAX_BYTES["correction"] + 1), "exceeds"),
    ],
)
def test_bad_corrections_rejected(payload, reason):
    with pytest.raises(ProtocolError, match=reason):
        decode("correction", payload)


@pytest.mark.parametrize(
    "over,reason",
    [
        ({"obs": np.zeros((4, 6), np.float32)}, "obs"),
        ({"obs": np.zeros((4, 5), np.float64)}, "dtype"),
        ({"action": np.full((4, 2), 2.0, np.float32)}, "outside"),
        ({"reward": np.array([0, 0, np.nan, 0], np.float32)}, "NaN"),
        ({"reward": np.zeros(3, np.float32)}, "rows"),
        ({"terminated": np.array([0, 2, 0, 0], np.uint8)}, "flags"),
        ({"first_step": -1}, "first_step"),
        ({"actor": "*"}, "bad identifier"),
    ],
)
def test_bad_transitions_rejected(over, reason):
    with pytest.raises(ProtocolError, match=reason):
        decode("transitions", _batch(**over))


def test_array_with_lying_shape_rejected():
    msg = msgpack.unpackb(_batch(), raw=False)
    msg["obs"]["shape"] = [8, 5]  # 8 rows claimed, 4 rows of bytes
    with pytest.raises(ProtocolError, match="bytes do not match"):
        decode("transitions", msgpack.packb(msg, use_bin_type=True))


def test_oversize_transitions_rejected_before_unpacking():
    with pytest.raises(ProtocolError, match="exceeds"):
        decode("transitions", b"\x00" * (MAX_BYTES["transitions"] + 1))


def test_weights_nan_rejected():
    bad = {"w": np.array([1.0, np.nan], np.float32)}
    with pytest.raises(ProtocolError, match="NaN"):
        decode("weights", encode("weights", "learner", 0, version=1, trained={}, tensors=bad))


def test_unknown_control_command_rejected():
    with pytest.raises(ProtocolError, match="unknown command"):
        decode("control", encode("control", "x", 0, command="format_disk"))


def test_pack_array_rejects_object_dtype():
    with pytest.raises(ProtocolError):
        pack_array(np.array([object()], dtype=object))


def test_keys_are_scoped_per_run():
    k = Keys("run1")
    assert k.transitions("a0") == "khgrl/run1/actor/a0/transitions"
    assert k.correction() == "khgrl/run1/human/*/correction"
    with pytest.raises(ValueError):
        Keys("bad/run")


def test_reject_counter_counts_by_kind():
    rc = RejectCounter("test")
    for payload in (b"junk", _raw(v=9)):
        try:
            decode("correction", payload)
        except ProtocolError as exc:
            rc.reject("correction", "k", exc)
    assert rc.by_kind() == {"correction": 2} and rc.total == 2
