"""The host's ends of a policy: how the game host asks for an action (``pipeline/play/rollout.py`` plays the episode).

- :class:`RemotePolicy`: a confined policy process (``pipeline/boundary/policy.py``), one round trip per step
  (over two pipes once the episode begins); the normal case (``pipeline/play/episodes.py`` starts the host and
  the policy process as a pair).
  Every byte it answers is bounded and checked here before it is believed: an action is a legal int, an error is
  capped text, node rows stay bytes for the parent to read within the episode's budget.
- :class:`LocalPolicy`: the policy loaded in this very process (``--workers 0``: debugging, no isolation at all).

Either way a policy that cannot give an action raises :class:`PolicyFailed` with the episode's end reason.
"""

from __future__ import annotations

import json
import marshal
import math
import random
import socket
import time
from typing import Any

import numpy as np

from pipeline.boundary.nodes import MAX_NODE_FRAME, node_budget
from pipeline.boundary.policy import (ACTION, MAX_ANSWER, MAX_NO_NODES_CHARS, Channel, capped_error, coerce_action,
                                     describe_exception, printed_text)
from pipeline.play.spec import EpisodeSpec
from tracing.capture import NodeRecorder, exception_message, exception_name
from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import CallTimer, PolicyTimeout

ANSWER_GRACE_S = 1.0
"""How long past its call limit the host waits for the policy process's answer (its own timer reports a slow
call at the limit; this catches one that defeated the timer or hangs in C)."""
LOAD_TIMEOUT_S = 60.0
"""How long the policy process may take to load the policy (less where the episode's own limit is less)."""
FINISH_TIMEOUT_S = 30.0
"""How long the policy process may take to send its node rows at the end, at most: never past the episode's own
time limit and :data:`ANSWER_GRACE_S` (a policy process that held its ``done`` back held its host 25 s an episode
past a 3 s limit, or, holding it longer, had the host killed and the steps it had played lost)."""


class PolicyFailed(Exception):
    """The policy could not give an action: ``end_reason`` (``policy_error``, ``timeout``, ``crashed``) and why."""

    def __init__(self, end_reason: str, error: str):
        super().__init__(error)
        self.end_reason, self.error = end_reason, error


class PolicyChannel:
    """How the host asks the policy for actions (see the module docstring)."""

    printed: str | None = None
    """What the policy printed in the episode :meth:`finish` ended (``EpisodeSpec.keep_printed``), or None."""

    def begin_loading(self) -> None:
        """Have the policy start loading, so that it loads while the host resets its environment (a policy process
        is another process); :meth:`start` then waits for it."""

    def start(self) -> None:
        """Load the policy, or wait until it is loaded (raises :class:`PolicyFailed`, e.g. for a policy file that
        does not load)."""

    def go(self, cpu: int | None, deadline: float = math.inf) -> None:
        """The episode begins (on ``cpu``, where the host now runs); its time is up at ``deadline``
        (``time.perf_counter()``)."""

    def act(self, obs: dict[str, Any]) -> int:
        """The policy's legal action for ``obs``; raises :class:`PolicyFailed`."""
        raise NotImplementedError

    def finish(self, more: bool = False, steps: int | None = None) -> Any:
        """The episode is over: the node rows (an Arrow table, the raw Arrow bytes of a remote policy, or None).
        ``more``: the next episode of the same game follows, played by the same policy (loaded, its state kept);
        ``steps``: the policy calls of the episode (its node rows' byte budget: ``nodes.node_budget``)."""
        return None


class LocalPolicy(PolicyChannel):
    """The policy in this process (``--workers 0``: for debugging; no isolation at all)."""

    def __init__(self, spec: EpisodeSpec, n_actions: int) -> None:
        self.spec, self.n_actions = spec, n_actions
        self.recorder = NodeRecorder(lines=spec.trace_lines) if spec.trace else None
        self.timer = CallTimer()
        self.policy: Any = None

    def start(self) -> None:
        random.seed(self.spec.policy_seed)
        np.random.seed(self.spec.policy_seed % 2**32)
        try:
            self.policy = load_policy(self.spec.policy_text, self.spec.policy_name).policy
        except PolicyLoadError as exc:
            raise PolicyFailed("policy_error", str(exc)) from None
        self.timer.__enter__()
        if self.recorder is not None:
            self.recorder.__enter__()
        self.step = -1

    def act(self, obs: dict[str, Any]) -> int:
        self.step += 1
        if self.recorder is not None:
            self.recorder.begin_step(self.step, obs)
        try:
            return coerce_action(self.timer.call(self.spec.call_time_limit_s or math.inf, self.policy, obs),
                                 self.n_actions)
        except PolicyTimeout as exc:
            raise PolicyFailed("timeout", describe_exception(exc)) from None
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - untrusted code: anything, SystemExit too
            raise PolicyFailed("policy_error", describe_exception(exc)) from None

    def finish(self, more: bool = False, steps: int | None = None) -> Any:
        if self.policy is not None:
            self.timer.__exit__(None, None, None)
            if self.recorder is not None:
                self.recorder.__exit__(None, None, None)
        nodes, failed = None, None
        if self.recorder is not None:
            try:
                nodes = self.recorder.table()
            except Exception as exc:  # noqa: BLE001 - as a policy process's rows that could not be made
                failed = no_trace("policy_error", f"its node rows could not be made ({exception_name(exc)}: "
                                                  f"{exception_message(exc, MAX_NO_NODES_CHARS)})")
        if more and self.policy is not None:  # the next episode: a new node log, the same policy object
            self.timer.__enter__()
            if self.recorder is not None:
                self.recorder = NodeRecorder(lines=self.spec.trace_lines).__enter__()
            self.step = -1
        if failed is not None:
            raise failed
        return nodes


class RemotePolicy(PolicyChannel):
    """The host's end of a confined policy process (``pipeline/boundary/policy.py``): one frame out and one back
    per step. Every answer is checked here: an action is a legal int, an error is capped text; a process that
    does not answer within its call limit (plus :data:`ANSWER_GRACE_S`), that sends anything else, or that dies,
    ends the episode (``timeout`` / ``crashed``) with the steps played so far."""

    def __init__(self, sock: socket.socket, spec: EpisodeSpec, n_actions: int) -> None:
        self.channel = Channel(sock, timed=True)
        self.spec, self.n_actions = spec, n_actions
        self.limit = (spec.call_time_limit_s or math.inf) + ANSWER_GRACE_S
        self.loading = False
        """The start message is sent (:meth:`begin_loading`)."""
        self.deadline = math.inf
        """When the episode's time is up (``time.perf_counter()``; :meth:`go`): no answer is awaited past it (plus
        :data:`ANSWER_GRACE_S`), so the host ends the episode itself, its steps kept, before the parent's kill."""
        self.broken = False
        """The stream is past use (no whole answer in time, a frame over its limit, the process gone): nothing more
        is read from it, not even the node rows at the end (what is left of a frame trickled a byte at a time would
        be read as the next)."""

    def _receive(self, timeout: float, what: str) -> tuple[bytes, bytes]:
        """The next answer, whole within ``timeout`` seconds (the frame's deadline, not each read's)."""
        timeout = None if math.isinf(timeout) else timeout
        try:
            return self.channel.receive(MAX_ANSWER, within=timeout)
        except TimeoutError:
            self.broken = True
            raise PolicyFailed("timeout", f"the policy process did not answer {what} within {timeout:.3g} s") from None
        except EOFError:
            self.broken = True
            raise PolicyFailed("crashed", f"the policy process ended {what}") from None
        except (OSError, ValueError) as exc:
            self.broken = True
            raise PolicyFailed("crashed", f"the policy process broke the protocol {what}: {exc}") from None

    def _failure(self, payload: bytes, what: str) -> PolicyFailed:
        try:
            message = json.loads(payload)
            reason, error = message["end_reason"], message["error"]
        except (ValueError, KeyError, TypeError, RecursionError):
            return PolicyFailed("crashed", f"the policy process sent a malformed message {what}")
        if message.get("kind") != "failed" or reason not in ("policy_error", "timeout") or not isinstance(error, str):
            return PolicyFailed("crashed", f"the policy process sent a malformed message {what}")
        return PolicyFailed(reason, capped_error(error))

    def begin_loading(self) -> None:
        spec = self.spec
        try:
            self.channel.send_json({
                "op": "start", "policy_text": spec.policy_text, "policy_name": spec.policy_name,
                "seed": spec.policy_seed, "trace": spec.trace, "trace_lines": spec.trace_lines,
                "call_time_limit_s": spec.call_time_limit_s, "n_actions": self.n_actions,
                "keep_printed": spec.keep_printed}, within=LOAD_TIMEOUT_S)
        except OSError:
            pass  # a policy process already gone: its EOF is the answer :meth:`start` reads
        self.loading = True

    def start(self) -> None:
        if not self.loading:
            self.begin_loading()
        # the load counts toward the episode's time (rollout.play_episode): never waited on past the episode's limit
        kind, payload = self._receive(min(LOAD_TIMEOUT_S, self.spec.episode_time_limit_s + ANSWER_GRACE_S),
                                      "while loading the policy")
        if kind == b"J" and payload == b'{"kind":"ready"}':
            return
        raise self._failure(payload, "while loading the policy") if kind == b"J" else \
            PolicyFailed("crashed", "the policy process sent a malformed message while loading the policy")

    def go(self, cpu: int | None, deadline: float = math.inf) -> None:
        self.deadline = deadline
        go = {"op": "go", "cpu": cpu}
        try:
            if self.channel.piped:  # the next episode of a continued game
                self.channel.send_json(go, within=self.limit)
            else:  # the first: it hands the policy process the pipes the episode's frames go over
                self.channel.send_handing_over(go, within=self.limit)
        except OSError:
            pass  # a policy process gone: the first step reads its EOF

    def act(self, obs: dict[str, Any]) -> int:
        try:
            self.channel.send(b"O", marshal.dumps(obs), self.limit)
        except OSError:
            raise PolicyFailed("crashed", "the policy process ended before the step") from None
        limit, what = self.limit, "at this step"
        left = self.deadline - time.perf_counter()
        if left + ANSWER_GRACE_S < limit:  # the episode's time is up first
            limit, what = max(left, 0.0) + ANSWER_GRACE_S, "at this step (the episode's time limit came first)"
        kind, payload = self._receive(limit, what)
        if kind == b"a" and len(payload) == ACTION.size:
            (action,) = ACTION.unpack(payload)
            if 0 <= action < self.n_actions:
                return action
            raise PolicyFailed("crashed", f"the policy process sent an illegal action {action}")
        raise self._failure(payload, "at this step") if kind == b"J" else \
            PolicyFailed("crashed", "the policy process sent a frame of an unknown kind")

    def close(self) -> None:
        """Let the policy process go (a game host that plays another episode next must not keep its socket)."""
        self.channel.close()

    def finish(self, more: bool = False, steps: int | None = None) -> bytes | None:
        """The node rows as the policy process sent them (an Arrow stream of at most the episode's byte budget,
        :func:`~pipeline.boundary.nodes.node_budget` of ``steps``, read and checked by the parent), or None.
        :class:`PolicyFailed` (``policy_error``, a malformed trace) for node rows the episode did not ask for
        (refused unread) or a node frame over the limit (refused at its header), and (:func:`no_trace`) for a traced
        episode's rows that do not arrive: the process ended, hung or broke the protocol at the end, or said its rows
        could not be made (such an episode was stored traced, with no node rows and no error). An untraced
        episode's steps are the host's: it is an episode whatever the process does at its end. None at once when
        the stream is :attr:`broken` (the host timed the process out: waiting for its node rows would only let it
        hold the host longer; the episode already ended by that)."""
        self.printed = None
        if self.broken:
            return None
        traced = self.spec.trace
        until = min(time.perf_counter() + FINISH_TIMEOUT_S, self.deadline + ANSWER_GRACE_S)

        def left() -> float:
            return max(until - time.perf_counter(), 0.0)

        try:
            self.channel.send_json({"op": "end", "more": more}, within=left())
            kind, payload = self._receive(left(), "at the episode's end")
            message = json.loads(payload) if kind == b"J" else None
        except PolicyFailed as exc:
            if traced:
                raise no_trace(exc.end_reason, f"{exc.error}, before sending its node rows") from None
            return None
        except (OSError, ValueError, RecursionError):
            if traced:
                raise no_trace("crashed", "the policy process broke the protocol at the end") from None
            return None
        if not isinstance(message, dict) or message.get("kind") != "done":
            if traced:
                raise no_trace("crashed", "the policy process sent another message where its node rows were due")
            return None
        if self.spec.keep_printed:
            self.printed = printed_text(message)
        if message.get("nodes") is not True:
            why = message.get("no_nodes")
            if traced:
                raise no_trace("policy_error", "the policy process sent no node rows" + (
                    f" ({capped_error(why[:MAX_NO_NODES_CHARS])})" if isinstance(why, str) and why else ""))
            return None
        if not traced:
            raise PolicyFailed("policy_error", "malformed trace: node rows for an episode that is not traced")
        try:
            budget = MAX_NODE_FRAME if steps is None else node_budget(steps)
            kind, payload = self.channel.receive(budget, within=left())
        except ValueError as exc:  # over the episode's byte budget, refused at the header
            raise PolicyFailed("policy_error", f"malformed trace: a node frame over the episode's budget ({exc})") \
                from None
        except TimeoutError:
            raise no_trace("timeout", "the policy process did not send its node rows in time") from None
        except (OSError, EOFError):
            raise no_trace("crashed", "the policy process ended while sending its node rows") from None
        if kind != b"A":
            raise no_trace("crashed", "the policy process sent another frame where its node rows were due")
        return payload


def no_trace(end_reason: str, why: str) -> PolicyFailed:
    """The failure of a traced episode whose node rows did not arrive (``trace missing: ...``): the episode's error
    says why it has no trace, and (as a malformed trace, ``pipeline/play/episodes.py`` ``trace_refused``) the
    episode is the policy's forfeit when it had played out; an earlier failure stays its error (it came first)."""
    return PolicyFailed(end_reason, f"trace missing: {why}")
