"""The typed wire protocol (common/wire/protocol.py, common/wire/messages.py, common/wire/checks.py): every message
class
round-trips, a sender cannot encode what receivers refuse, and every kind of bad message is rejected with a
reason (never an unexpected exception). Hostile payloads are built with msgpack directly, as a stranger on the
router would."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import msgpack
import numpy as np
import pytest
from khgrl.common.tasks.spaces import ACT_DIM, OBS_DIM
from khgrl.common.wire.messages import ActorInfo, Dims, HumanInfo, LearnerInfo, TaskInfo
from khgrl.common.wire.protocol import (
    KINDS,
    SCHEMA_VERSION,
    Ack,
    Control,
    Correction,
    EpisodeReport,
    Frame,
    Keys,
    Message,
    ProtocolError,
    RejectCounter,
    Scale,
    Status,
    Transitions,
    Weights,
    decode,
    decode_any,
    encode,
    pack_array,
    with_base_seq,
)

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------ sample messages
def _transitions(n: int = 4, **over) -> Transitions:
    rng = np.random.default_rng(0)
    fields = dict(
        actor="a0",
        first_step=0,
        obs=rng.uniform(size=(n, OBS_DIM)).astype(np.float32),
        next_obs=rng.uniform(size=(n, OBS_DIM)).astype(np.float32),
        action=rng.uniform(-1, 1, size=(n, ACT_DIM)).astype(np.float32),
        reward=rng.normal(size=n).astype(np.float32),
        terminated=np.zeros(n, np.uint8),
        truncated=np.zeros(n, np.uint8),
        intervened=np.array([1, 0, 0, 1][:n] + [0] * max(0, n - 4), np.uint8),
        clipped=np.zeros(n, np.uint8),
        task="0123456789abcdef",
    )
    fields.update(over)
    return Transitions(**fields)


def _frame(**over) -> Frame:
    fields = dict(actor="a0", episode=1, t=3, phase=0.1, robot=np.array([0.1, 0.2]), desired=np.array([0.1, 0.25]),
                  mean=np.array([0.1, 0.3]), scale=np.array([20.0, 20.0]), intervening=False, task="passage-high_cov")
    fields.update(over)
    return Frame(**fields)


def _actor_info(**over) -> ActorInfo:
    fields = dict(id="a0", episode=2, t=17, transitions=500, sent=9, next_seq=10, outbox=2, received=8, durable=5,
                  trained=480, weights_version=3, ack_version=3, learner_alive=True, waits=1, wait_s=0.25, resends=0,
                  corrections={"applied": 3, "stale": 1}, intervening=False, rejects={}, paused=False,
                  period_ms_p50=20.1)
    fields.update(over)
    return ActorInfo(**fields)


def _learner_info(**over) -> LearnerInfo:
    fields = dict(id="learner", epoch="e1", ingested=500, iterations=60, gradient_steps=480, grad_steps_per_s=95.5,
                  version=3, pending_iterations=0, queue_depth=1, rejects={"transitions": 2}, paused=False,
                  checkpoints=1, next_seq={"a0": 10}, durable={"a0": 5}, duplicates={}, weights_queries=4)
    fields.update(over)
    return LearnerInfo(**fields)


def _human_info(**over) -> HumanInfo:
    fields = dict(frames=120, corrections=7, rejects={})
    fields.update(over)
    return HumanInfo(**fields)


def _samples() -> list[Message]:
    """One instance of every message class, with optional fields both absent and present."""
    return [
        _transitions(),
        _transitions(n=1, first_step=96, base_seq=2, stream="s1"),
        Ack(actor="a0", received=7, durable=5, trained=480, version=3, epoch="e1"),
        Ack(actor="a0", received=-1, durable=-1, trained=0, version=0, epoch="e1", stream="s1"),
        Weights(version=7, trained={"a0": 104}, tensors={"latent_pi.0.weight": np.ones((256, OBS_DIM), np.float32),
                                                         "mu.bias": np.zeros(ACT_DIM, np.float32)}),
        Weights(version=0, trained={}, tensors={"w": np.zeros((2, 3, 4), np.float32)}, epoch="e1"),
        Correction(client="pad", actor="a0", active=True, p_h=np.array([0.2, 0.7])),
        Correction(client="pad", actor="a0", active=False),
        Correction(client="pad", actor="a0", active=True, p_h=np.array([0.2, 0.7]), episode=4, t=16, step=17),
        _frame(),
        _frame(ret=-12.5, next_mean=np.array([0.3, 0.4]), intervening=True, last=True),
        _frame(t=0, phase=0.0, last=False),
        Scale(actor="a0", model={"l0": [20.0, 20.0], "x": [0.1, 0.2]}),
        Scale(actor="a0", model={}, table=np.full((400, ACT_DIM), 15.0)),
        EpisodeReport(actor="a0", stats={"episode": 3, "steps": 400, "ret": 150.5, "success": True, "failure": False,
                                         "scale_max": [15.0, 20.0]}),
        Status(role="actor", info=_actor_info()),
        Status(role="actor", info=_actor_info(period_ms_p50=None)),
        Status(role="learner", info=_learner_info()),
        Status(role="human", info=_human_info()),
        *[Control(command=c) for c in ("pause", "resume", "stop", "checkpoint")],
        TaskInfo(sender_id="a0", descriptor=_descriptor()),
    ]


def _descriptor():
    from khgrl.common.tasks.passage.env import PassageEnv

    return PassageEnv("high_cov").descriptor("passage:high_cov")


def _assert_same(a, b, where: str = "") -> None:
    """Field-by-field equality with exact arrays (values and dtype) and nested maps."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            if f.name != "envelope":
                _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and b.dtype == a.dtype, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}[{k}]")
    else:
        assert a == b and type(a) is type(b), (where, a, b)


def _raw(kind: str = "correction", **over) -> bytes:
    """A hand-made payload (``...`` leaves a field out)."""
    msg = {"v": SCHEMA_VERSION, "kind": kind, "sender": "pad", "seq": 0, "ts": 1.0, "client": "pad", "actor": "a0",
           "active": True, "p_h": [0.5, 0.5]}
    msg.update(over)
    return msgpack.packb({k: v for k, v in msg.items() if v is not ...}, use_bin_type=True)


def _status_raw(role: str, info: dict) -> bytes:
    return _raw("status", role=role, info=info, client=..., actor=..., active=..., p_h=...)


# ------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("msg", _samples(), ids=lambda m: type(m).__name__)
def test_every_message_class_round_trips(msg: Message) -> None:
    payload = encode(msg, "sender-1", 12, ts=3.5)
    out = decode(type(msg), payload)
    _assert_same(msg, out)
    env = out.envelope
    assert (env.kind, env.sender, env.seq, env.ts) == (msg.KIND, "sender-1", 12, 3.5)
    # decode_any picks the class by kind name
    _assert_same(msg, decode_any(msg.KIND, payload))


def test_samples_cover_every_kind() -> None:
    assert {type(m) for m in _samples()} == set(KINDS.values())


def test_transitions_round_trip_keeps_dtypes_and_rows() -> None:
    msg = decode(Transitions, encode(_transitions(), "a0", 3))
    assert msg.envelope.seq == 3 and msg.actor == "a0" and msg.n == 4
    assert msg.obs.shape == (4, OBS_DIM) and msg.obs.dtype == np.float32
    np.testing.assert_array_equal(msg.intervened, [1, 0, 0, 1])


def test_optional_fields_are_left_out_of_the_payload() -> None:
    raw = msgpack.unpackb(encode(Correction(client="pad", actor="a0", active=False), "pad", 1), raw=False)
    assert set(raw) == {"v", "kind", "sender", "seq", "ts", "client", "actor", "active"}
    rel = decode(Correction, encode(Correction(client="pad", actor="a0", active=False), "pad", 1))
    assert rel.p_h is None and rel.step is None


def test_frame_last_round_trips_and_is_optional() -> None:
    assert decode(Frame, encode(_frame(), "a0", 0)).last is None
    assert decode(Frame, encode(_frame(last=True), "a0", 1)).last is True
    assert decode(Frame, encode(_frame(last=False), "a0", 2)).last is False
    with pytest.raises(ProtocolError, match="last"):
        decode(Frame, _frame_wire(last=1))  # a boolean, not 0/1


def _frame_wire(**over) -> bytes:
    m = msgpack.unpackb(encode(_frame(), "a0", 0), raw=False)
    m.update(over)
    return msgpack.packb(m, use_bin_type=True)


def test_frame_next_mean_is_checked() -> None:
    np.testing.assert_allclose(decode(Frame, encode(_frame(next_mean=np.array([0.3, 0.4])), "a0", 1)).next_mean,
                               [0.3, 0.4])
    with pytest.raises(ProtocolError, match="next_mean"):
        decode(Frame, _frame_wire(next_mean=[0.3, float("nan")]))


# ------------------------------------------------------------------------------------ schema version
@pytest.mark.parametrize("v", [1.0, True, 0, SCHEMA_VERSION + 1, "1", None, ...])
def test_schema_version_must_be_the_integer_1(v) -> None:
    with pytest.raises(ProtocolError, match="schema version"):
        decode(Correction, _raw(v=v))
    with pytest.raises(ProtocolError, match="schema version"):
        decode_any("correction", _raw(v=v))


def test_schema_version_1_is_accepted() -> None:
    assert SCHEMA_VERSION == 1 and type(SCHEMA_VERSION) is int
    assert decode(Correction, _raw(v=1)).active is True


# ------------------------------------------------------------------------------------ senders are checked
@pytest.mark.parametrize(
    "msg,reason",
    [
        (Correction(client="pad", actor="a0", active=True, p_h=np.array([0.5, np.nan])), "not finite"),
        (Correction(client="pad", actor="a0", active=True, p_h=np.array([0.5, np.inf])), "not finite"),
        (Correction(client="pad", actor="a0", active=True, p_h=np.zeros(65)), "p_h"),
        (Correction(client="pad", actor="a0", active=False, step=3), "needs its episode"),
        (Correction(client="a/b", actor="a0", active=False), "bad identifier"),
        (_transitions(action=np.full((4, ACT_DIM), 1.5, np.float32)), "outside"),
        (_transitions(reward=np.array([0, 0, np.nan, 0], np.float32)), "NaN"),
        (_transitions(obs=np.zeros((4, OBS_DIM), np.float64)), "dtype"),
        (_transitions(reward=np.zeros(3, np.float32)), "rows"),
        (_transitions(base_seq=9), "base_seq"),
        (_transitions(task=None), "task: missing"),
        (_frame(phase=1.5), "phase"),
        (_frame(robot=np.array([0.1, np.nan])), "not finite"),
        (Weights(version=1, trained={}, tensors={"w": np.array([1.0, np.nan], np.float32)}), "NaN"),
        (Weights(version=1, trained={}, tensors={}), "tensors"),
        (Control(command="format_disk"), "unknown command"),
        (EpisodeReport(actor="a0", stats={"episode": 0}), "stats.episode"),
        (EpisodeReport(actor="a0", stats={"episode": 1, "scale_max": [15.0, float("nan")]}), "not finite"),
        (Ack(actor="a0", received=-2, durable=0, trained=0, version=0, epoch="e"), "received"),
    ],
    ids=lambda x: type(x).__name__ if isinstance(x, Message) else x,
)
def test_a_sender_cannot_encode_an_invalid_message(msg: Message, reason: str) -> None:
    with pytest.raises(ProtocolError, match=reason):
        encode(msg, "s", 5)


def test_encode_checks_the_envelope_and_the_class() -> None:
    ok = Control(command="stop")
    with pytest.raises(ProtocolError, match="sender"):
        encode(ok, "bad sender", 0)
    with pytest.raises(ProtocolError, match="seq"):
        encode(ok, "s", -1)
    with pytest.raises(TypeError):
        encode({"kind": "control", "command": "stop"}, "s", 0)  # type: ignore[arg-type]


def test_status_needs_the_info_class_of_its_role() -> None:
    with pytest.raises(ProtocolError, match="needs a ActorInfo"):
        Status(role="actor", info=_human_info())
    with pytest.raises(ProtocolError):
        Status(role="viewer", info=_human_info())


# ------------------------------------------------------------------------------------ status info schema
ROLE_INFO = {"actor": _actor_info, "learner": _learner_info, "human": _human_info}


@pytest.mark.parametrize("role", sorted(ROLE_INFO))
def test_status_info_round_trips_per_role(role: str) -> None:
    info = dataclasses.asdict(ROLE_INFO[role]())
    out = decode(Status, _status_raw(role, info))
    assert out.role == role and dataclasses.asdict(out.info) == info


@pytest.mark.parametrize("role", sorted(ROLE_INFO))
def test_status_info_with_an_unknown_field_is_rejected(role: str) -> None:
    info = dataclasses.asdict(ROLE_INFO[role]())
    info["surprise"] = 1
    with pytest.raises(ProtocolError, match="unknown fields"):
        decode(Status, _status_raw(role, info))


@pytest.mark.parametrize("role", sorted(ROLE_INFO))
def test_status_info_with_a_missing_field_is_rejected_for_every_field(role: str) -> None:
    full = dataclasses.asdict(ROLE_INFO[role]())
    for name in full:
        info = {k: v for k, v in full.items() if k != name}
        with pytest.raises(ProtocolError, match=f"info.{name}: missing"):
            decode(Status, _status_raw(role, info))


@pytest.mark.parametrize(
    "role,field,value",
    [
        ("actor", "episode", 1.5),
        ("actor", "learner_alive", 1),
        ("actor", "corrections", {"applied": "3"}),
        ("actor", "wait_s", float("nan")),
        ("learner", "epoch", 7),
        ("learner", "next_seq", [1, 2]),
        ("human", "frames", True),
    ],
)
def test_status_info_with_a_wrong_type_is_rejected(role: str, field: str, value) -> None:
    info = dataclasses.asdict(ROLE_INFO[role]())
    info[field] = value
    with pytest.raises(ProtocolError, match=field):
        decode(Status, _status_raw(role, info))


def test_status_of_an_unknown_role_is_rejected() -> None:
    with pytest.raises(ProtocolError, match="role"):
        decode(Status, _status_raw("viewer", dataclasses.asdict(_human_info())))


# ------------------------------------------------------------------------------------ decode_any, with_base_seq
def test_decode_any_dispatches_by_kind_and_rejects_unknown_kinds() -> None:
    msg = decode_any("control", encode(Control(command="pause"), "x", 0))
    assert isinstance(msg, Control) and msg.command == "pause"
    with pytest.raises(ProtocolError, match="unknown message kind"):
        decode_any("telepathy", encode(Control(command="pause"), "x", 0))
    with pytest.raises(ProtocolError, match="kind"):
        decode_any("frame", encode(Control(command="pause"), "x", 0))  # a control payload on a frame topic


def test_with_base_seq_restamps_only_base_seq() -> None:
    payload = encode(_transitions(base_seq=1, stream="s1"), "a0", 5, ts=2.0)
    new = decode(Transitions, with_base_seq(payload, 3))
    assert new.base_seq == 3
    assert (new.envelope.sender, new.envelope.seq, new.envelope.ts) == ("a0", 5, 2.0)
    _assert_same(_transitions(base_seq=3, stream="s1"), new)
    assert decode(Transitions, with_base_seq(payload, 5)).base_seq == 5  # base_seq == seq is allowed
    with pytest.raises(ProtocolError, match="base_seq"):
        with_base_seq(payload, 6)  # never beyond the batch's own seq
    with pytest.raises(ProtocolError):
        with_base_seq(encode(Control(command="stop"), "x", 0), 0)  # not a transitions payload


# ------------------------------------------------------------------------------------ hostile payloads
@pytest.mark.parametrize(
    "payload,reason",
    [
        (b"", "not msgpack"),
        (b"\xc1\xff\x00garbage", "not msgpack"),
        (msgpack.packb([1, 2, 3]), "not a map"),
        (_raw(kind="frame"), "kind"),
        (_raw(sender="a/b"), "bad identifier"),
        (_raw(sender=""), "bad identifier"),
        (_raw(seq=-1), "seq"),
        (_raw(seq="3"), "seq"),
        (_raw(seq=True), "seq"),
        (_raw(ts=float("nan")), "ts"),
        (_raw(active="yes"), "active"),
        (_raw(p_h=[]), "p_h"),
        (_raw(p_h=[0.5, float("nan")]), "not finite"),
        (_raw(p_h=[0.5, float("inf")]), "not finite"),
        (_raw(p_h=["a", 0.5]), "p_h"),
        (_raw(actor=...), "actor"),
        (_raw(step=3), "needs its episode"),
        (_raw(step=-1, episode=1), "step"),
        (_raw(step=1.5, episode=1), "step"),
        (b"\x00" * (Correction.MAX_BYTES + 1), "exceeds"),
        ("not bytes", "not bytes"),
    ],
)
def test_bad_corrections_rejected(payload, reason: str) -> None:
    with pytest.raises(ProtocolError, match=reason):
        decode(Correction, payload)


def _transitions_wire(**over) -> bytes:
    m = msgpack.unpackb(encode(_transitions(), "a0", 3), raw=False)
    m.update({k: pack_array(v) if isinstance(v, np.ndarray) else v for k, v in over.items()})
    return msgpack.packb(m, use_bin_type=True)


@pytest.mark.parametrize(
    "over,reason",
    [
        ({"obs": np.zeros((4, OBS_DIM + 1), np.float32)}, "obs"),
        ({"obs": np.zeros((4, OBS_DIM), np.float64)}, "dtype"),
        ({"action": np.full((4, ACT_DIM), 2.0, np.float32)}, "outside"),
        ({"reward": np.array([0, 0, np.nan, 0], np.float32)}, "NaN"),
        ({"reward": np.zeros(3, np.float32)}, "rows"),
        ({"terminated": np.array([0, 2, 0, 0], np.uint8)}, "flags"),
        ({"first_step": -1}, "first_step"),
        ({"actor": "*"}, "bad identifier"),
        ({"base_seq": 4}, "base_seq"),
        ({"obs": "pickle"}, "not an array map"),
    ],
)
def test_bad_transitions_rejected(over: dict, reason: str) -> None:
    with pytest.raises(ProtocolError, match=reason):
        decode(Transitions, _transitions_wire(**over))


def test_array_with_lying_shape_rejected() -> None:
    msg = msgpack.unpackb(encode(_transitions(), "a0", 3), raw=False)
    msg["obs"]["shape"] = [8, OBS_DIM]  # 8 rows claimed, 4 rows of bytes
    with pytest.raises(ProtocolError, match="bytes do not match"):
        decode(Transitions, msgpack.packb(msg, use_bin_type=True))


def test_oversize_transitions_rejected_before_unpacking() -> None:
    with pytest.raises(ProtocolError, match="exceeds"):
        decode(Transitions, b"\x00" * (Transitions.MAX_BYTES + 1))


def test_pack_array_rejects_object_dtype() -> None:
    with pytest.raises(ProtocolError):
        pack_array(np.array([object()], dtype=object))


# ------------------------------------------------------------------------------------ keys, reject counter
def test_keys_are_scoped_per_run() -> None:
    k = Keys("run1")
    assert k.transitions("a0") == "khgrl/run1/actor/a0/transitions"
    assert k.correction() == "khgrl/run1/human/*/correction"
    assert k.status("actor", "a0") == "khgrl/run1/status/actor/a0"
    assert Keys.chunk("khgrl/run1/actor/a0/frame", 3) == "a0"
    with pytest.raises(ValueError):
        Keys("bad/run")


def test_reject_counter_counts_by_kind() -> None:
    rc = RejectCounter("test")
    for payload in (b"junk", _raw(v=9)):
        try:
            decode(Correction, payload)
        except ProtocolError as exc:
            rc.reject("correction", "k", exc)
    assert rc.by_kind() == {"correction": 2} and rc.total == 2


def test_reject_logging_is_rate_limited_under_a_flood_of_distinct_garbage(caplog) -> None:
    """100,000 random payloads (a new reason nearly every time): a handful of lines, every reject counted, and a
    bounded number of reasons kept."""
    now = [0.0]
    rc = RejectCounter("test", first=5, every=10.0, max_reasons=32, clock=lambda: now[0])
    rng = np.random.default_rng(0)
    with caplog.at_level("WARNING", logger="khgrl.protocol"):
        for i in range(100_000):
            now[0] = i * 2.5e-4  # 25 s in all
            try:
                decode(Correction, rng.bytes(int(rng.integers(1, 40))))
            except ProtocolError as exc:
                rc.reject("correction", "k", exc)
    assert rc.by_kind() == {"correction": 100_000}
    assert rc.logged == len(caplog.records) <= 5 + 2  # the first 5 reasons, then one line per 10 s
    assert len([k for k in rc.counts if isinstance(k, tuple)]) <= 33  # 32 reasons + "other"
    assert "since the last line" in caplog.records[-1].getMessage()


# ------------------------------------------------------------------------------------ one place for msgpack
PACKAGES = ("common", "actor", "learner", "human_bridge", "deploy", "benchmarks")
THIRD_PARTY = REPO / "deploy" / "examples"  # an example client written without our code: it must use msgpack


def imports_package(tree: ast.AST, package: str) -> bool:
    """Whether a module's syntax tree imports ``package`` (or a module of it) anywhere in the file."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == package for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == package:
            return True
    return False


def _imports_msgpack(path: Path) -> bool:
    return imports_package(ast.parse(path.read_text(), filename=str(path)), "msgpack")


def test_nothing_but_the_wire_protocol_imports_msgpack() -> None:
    offenders = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            # (common/wire/control.py: the control payload without numpy, for khgrl stop --now's quick start)
            if THIRD_PARTY in path.parents or path in (REPO / "common" / "wire" / "protocol.py",
                                                       REPO / "common" / "wire" / "control.py"):
                continue
            if _imports_msgpack(path):
                offenders.append(str(path.relative_to(REPO)))
    assert offenders == [], f"msgpack imported outside common/wire/protocol.py and control.py: {offenders}"
    assert _imports_msgpack(REPO / "common" / "wire" / "protocol.py")


# ------------------------------------------------------------------------------------ sizes from the task
def test_sizes_any_but_consistent_without_a_task() -> None:
    """Without the receiver's sizes, any O (here 3) and observation size pass if the message agrees with itself."""
    n = 4
    tr = _transitions().replace(obs=np.zeros((n, 9), np.float32), next_obs=np.zeros((n, 9), np.float32),
                                action=np.zeros((n, 3), np.float32))
    msg = decode(Transitions, encode(tr, "a0", 3))
    assert msg.obs.shape == (n, 9) and msg.action.shape == (n, 3)
    with pytest.raises(ProtocolError, match="obs"):
        decode(Transitions, encode(tr, "a0", 3), Dims(obs=OBS_DIM, out=ACT_DIM))
    with pytest.raises(ProtocolError, match="action"):
        decode(Transitions, encode(tr, "a0", 3), Dims(obs=9, out=2))
    assert decode(Transitions, encode(tr, "a0", 3), Dims(obs=9, out=3)).n == n


def test_frame_and_correction_sizes_checked_against_the_task() -> None:
    p3 = np.array([0.1, 0.2, 0.3])
    f = Frame(actor="a0", episode=1, t=0, phase=0.0, robot=p3, desired=p3, mean=p3, scale=p3, intervening=False,
              task="own")
    assert decode(Frame, encode(f, "a0", 0)).robot.shape == (3,)
    with pytest.raises(ProtocolError, match="robot"):
        decode(Frame, encode(f, "a0", 0), Dims(out=2))
    ragged = msgpack.unpackb(encode(f, "a0", 0), raw=False)
    ragged["mean"] = [0.1, 0.2]
    with pytest.raises(ProtocolError, match="mean"):
        decode(Frame, msgpack.packb(ragged, use_bin_type=True))
    c = Correction(client="h", actor="a0", active=True, p_h=p3)
    assert decode(Correction, encode(c, "h", 0), Dims(out=3)).p_h.shape == (3,)
    with pytest.raises(ProtocolError, match="p_h"):
        decode(Correction, encode(c, "h", 0), Dims(out=2))
