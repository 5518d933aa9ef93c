"""The key expressions of a run (docs/protocol.md, "Keys"): everything lives under ``khgrl/<run>/``. Lean (no
numpy): ``khgrl stop --now`` needs them before anything heavy is loaded; :mod:`khgrl.common.wire.protocol` re-exports
:class:`Keys`."""

from __future__ import annotations

__all__ = ["Keys", "MAX_ID_LEN"]

MAX_ID_LEN = 64  # the longest id (run, actor, client, sender) a key chunk may be


class Keys:
    """Key expressions of one run: everything lives under ``khgrl/<run>/``."""

    def __init__(self, run: str) -> None:
        if not run or any(c in run for c in "/*$?# ") or len(run) > MAX_ID_LEN:
            raise ValueError(f"run id must be a non-empty key chunk without / * $ ? # or space, got {run!r}")
        self.run = run
        self.root = f"khgrl/{run}"

    def transitions(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/transitions"

    def frame(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/frame"

    def scale(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/scale"

    def episode(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/episode"

    def ack(self, actor: str = "*") -> str:
        return f"{self.root}/learner/ack/{actor}"

    @property
    def weights(self) -> str:
        return f"{self.root}/learner/weights"

    def correction(self, client: str = "*") -> str:
        return f"{self.root}/human/{client}/correction"

    def status(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.root}/status/{role}/{ident}"

    def control(self, target: str = "*") -> str:
        return f"{self.root}/control/{target}"

    def task(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.root}/task/{role}/{ident}"

    def alive(self, role: str = "*", ident: str = "*") -> str:
        """A liveliness token ``alive/<role>/<id>`` (the learner's carries its epoch: :meth:`learner_alive`)."""
        return f"{self.root}/alive/{role}/{ident}"

    def learner_alive(self, ident: str = "*", epoch: str = "*") -> str:
        """The learner's liveliness token ``alive/learner/<id>/<epoch>``: which incarnation is alive."""
        return f"{self.root}/alive/learner/{ident}/{epoch}"

    @property
    def learners_alive(self) -> str:
        """Every learner's liveliness token, with or without the epoch chunk (subscribe or query this)."""
        return f"{self.root}/alive/learner/**"

    def request(self, actor: str = "*") -> str:
        """An actor's requests to the learner (a ``control`` message; only ``checkpoint`` is accepted)."""
        return f"{self.root}/actor/{actor}/request"

    def human_request(self, client: str = "*") -> str:
        """A human-input client's requests to the actors (a ``control`` message; only ``pause`` and ``resume``)."""
        return f"{self.root}/human/{client}/request"

    @staticmethod
    def chunk(key: str, index: int) -> str:
        """One chunk of a key: ``chunk("khgrl/r/actor/a0/frame", 3) == "a0"``."""
        return str(key).split("/")[index]

    last_chunk = chunk  # (older name)
