"""The task descriptor's ``cameras`` (common/wire/descriptor.py) and the learner's spaces built from it
(common/tasks/spaces.py): a camera task's descriptor names its images, round-trips through msgpack, and gives the
Dict space its actor's KGRLEnv observes; a vector task's wire map and digest have no trace of the field; malformed
camera entries are refused with a ProtocolError naming what is wrong."""

from __future__ import annotations

import hashlib
import json
from dataclasses import fields

import msgpack
import numpy as np
import pytest
from gymnasium import spaces
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.env_descriptor import descriptor
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.spaces import observation_space
from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.descriptor import MAX_CAMERAS, MAX_SIDE, TaskDescriptor
from khgrl.deploy.examples.camera_task import SIDE, make_task


@pytest.fixture(scope="module")
def camera_env() -> KGRLEnv:
    return KGRLEnv(make_task(), seed=0)


@pytest.fixture(scope="module")
def vector_env() -> KGRLEnv:
    return KGRLEnv(load_task("passage:high_cov"), seed=0)


def _roundtrip(d: TaskDescriptor) -> TaskDescriptor:
    return TaskDescriptor.from_wire(msgpack.unpackb(msgpack.packb(d.to_wire(), use_bin_type=True), raw=False))


def _legacy_digest(d: TaskDescriptor) -> str:
    """The digest as computed before the descriptor had ``cameras``."""
    skip = ("mean", "demos", "projector", "cameras")
    text = json.dumps({f.name: getattr(d, f.name) for f in fields(d) if f.name not in skip}, sort_keys=True,
                      default=list)
    h = hashlib.sha256(text.encode())
    h.update(np.ascontiguousarray(d.demos, dtype="<f8").tobytes())
    return h.hexdigest()[:16]


def test_vector_descriptor_unchanged(vector_env: KGRLEnv) -> None:
    d = descriptor(vector_env, "passage:high_cov")
    assert d.cameras == {} and "cameras" not in d.to_wire()
    assert d.digest == _legacy_digest(d)
    back = _roundtrip(d)
    assert back.cameras == {} and back.digest == d.digest
    assert isinstance(observation_space(d), spaces.Box) and observation_space(d) == vector_env.observation_space


def test_camera_descriptor_names_its_images(camera_env: KGRLEnv) -> None:
    d = descriptor(camera_env, "khgrl.deploy.examples.camera_task:make_task")
    assert d.cameras == {"cam": (SIDE, SIDE, 3)} and d.obs_dim == 2 + 1 + 2
    assert d.to_wire()["cameras"] == {"cam": [SIDE, SIDE, 3]}
    back = _roundtrip(d)
    assert back.cameras == d.cameras and back.digest == d.digest
    assert d.digest != _legacy_digest(d)  # the cameras are part of what actor and learner agree on
    space = observation_space(back)
    assert isinstance(space, spaces.Dict) and space == camera_env.observation_space
    obs, _ = camera_env.reset(seed=1)
    assert space.contains(obs)


@pytest.mark.parametrize(("cameras", "words"), [
    ({}, "1..4 cameras"),
    ([["cam", [4, 4, 3]]], "a map"),
    ({f"c{k}": [4, 4, 3] for k in range(MAX_CAMERAS + 1)}, "1..4 cameras"),
    ({"state": [4, 4, 3]}, "'state'"),
    ({"a/b": [4, 4, 3]}, "'a/b'"),
    ({"x" * 33: [4, 4, 3]}, "short identifier"),
    ({"cam": [4, 4]}, "cameras[cam]: expected [H, W, C]"),
    ({"cam": [4, 4, 3.0]}, "cameras[cam]: expected [H, W, C]"),
    ({"cam": [MAX_SIDE + 1, 4, 3]}, "cameras[cam]: shape"),
    ({"cam": [0, 4, 3]}, "cameras[cam]: shape"),
    ({"cam": [4, 4, 2]}, "C in"),
])
def test_malformed_cameras_refused(camera_env: KGRLEnv, cameras, words: str) -> None:
    m = descriptor(camera_env).to_wire()
    m["cameras"] = cameras
    with pytest.raises(ProtocolError, match="cameras") as err:
        TaskDescriptor.from_wire(m)
    assert words in str(err.value), str(err.value)
