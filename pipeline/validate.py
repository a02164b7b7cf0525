"""Validation of a candidate policy proposed by the LLM, before it becomes a policy version.

Static checks, in the parent (no candidate code runs there): every suggested method exists and is trainable;
its source is one ``def`` of the same name with the same parameters; it passes the sandbox's source check;
spliced into the policy file, the whole file still checks, and fits half of the prompt's token budget
(:func:`check_fits`). Then a runtime check in a hardened worker process:
the candidate policy is loaded and called on observations recorded in the store (the training rollout's),
each call within the time limit and returning a legal action. The first failure rejects the candidate with a
reason that names the method, the error and, for runtime failures, the step whose observation broke it; the
reason (capped and scrubbed of secrets, ``pipeline/untrusted.py``) becomes part of the next feedback.
"""

from __future__ import annotations

import ast
import time
from dataclasses import dataclass
from typing import Any

from games import get_game
from pipeline.executor import run_tasks
from pipeline.rollout import coerce_action, describe_exception
from pipeline.untrusted import clean_untrusted_text
from tracing.policy_file import PolicyInfo, PolicyLoadError, inspect_policy, load_policy, replace_methods
from tracing.sandbox import CallTimer, PolicyCodeError, PolicyTimeout, check_source

MAX_VALIDATION_STEPS = 200
"""Recorded observations a candidate is run on (evenly spread over the rollout)."""


class CandidateRejected(Exception):
    """A candidate that must not become a policy version; ``str()`` is the reason, cleaned as untrusted text
    (``pipeline/untrusted.py``: capped, secrets redacted): it quotes the candidate's own exceptions and names."""

    def __init__(self, reason: object):
        super().__init__(clean_untrusted_text(reason))


@dataclass
class Candidate:
    text: str
    sources: dict[str, str]
    info: PolicyInfo

    @property
    def version_id(self) -> str:
        return self.info.version_id


def _arguments(source: str) -> str:
    node = ast.parse(source).body[0]
    args = node.args
    for a in args.posonlyargs + args.args + args.kwonlyargs + [args.vararg, args.kwarg]:
        if a is not None:
            a.annotation = None  # annotations may change; names, order, kinds and defaults may not
    return ast.unparse(args)


def build_candidate(info: PolicyInfo, suggestion: dict[str, str]) -> Candidate | None:
    """The candidate policy text for ``suggestion`` (static checks), or None if it changes nothing."""
    methods = {m.name: m for m in info.methods}
    trainable = [m.name for m in info.trainable]
    changed: dict[str, str] = {}
    for name, source in suggestion.items():
        if name not in methods:
            raise CandidateRejected(f"the suggestion is for '{name}', which the policy does not have; "
                                    f"trainable methods: {', '.join(trainable)}")
        if not methods[name].trainable:
            raise CandidateRejected(f"'{name}' is not trainable; only {', '.join(trainable)} may change")
        try:
            tree = ast.parse(source)
        except SyntaxError as exc:
            raise CandidateRejected(f"the new {name} does not parse: {exc.msg} at line {exc.lineno}") from None
        defs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
        if len(defs) != 1 or len(tree.body) != 1:
            raise CandidateRejected(f"the new {name} must be exactly one 'def {name}(...)' and nothing else")
        if defs[0].name != name:
            raise CandidateRejected(f"the code given for {name} defines '{defs[0].name}' instead")
        old_args, new_args = _arguments(methods[name].source), _arguments(source)
        if old_args != new_args:
            raise CandidateRejected(f"{name} must keep its parameters ({old_args}) but the new code has ({new_args})")
        try:
            check_source(source, name)
        except PolicyCodeError as exc:
            raise CandidateRejected(f"the new {name} is refused: {str(exc).split(': ', 1)[-1]}") from None
        if source.strip() != methods[name].source.strip():
            changed[name] = source
    if not changed:
        return None
    text = replace_methods(info.text, changed)
    try:
        new_info = inspect_policy(text, info.name)
    except PolicyLoadError as exc:
        raise CandidateRejected(f"the policy with the new code does not check: {exc}") from None
    return Candidate(text, changed, new_info)


CODE_BUDGET_SHARE = 0.5
"""Most of the prompt's token budget a candidate policy's text may take (the next prompt shows it whole)."""


def check_fits(candidate: Candidate, token_budget: int, count) -> None:
    """:class:`CandidateRejected` if the candidate's policy text would take more than :data:`CODE_BUDGET_SHARE`
    of the next prompt's token budget (``count``: text -> tokens). Without this, one long reply that validates
    (a method with a megabyte docstring) would make every later prompt impossible to build."""
    limit = int(token_budget * CODE_BUDGET_SHARE)
    if len(candidate.text) > 8 * limit:  # too long whatever the tokenizer: do not even count it
        raise CandidateRejected(f"the new code is {len(candidate.text):,} characters long, far more than the "
                                f"{limit:,} tokens of the prompt it may take; keep the methods short")
    tokens = count(candidate.text)
    if tokens > limit:
        raise CandidateRejected(f"the new code is {tokens:,} tokens long, more than the {limit:,} tokens of the "
                                f"prompt it may take ({CODE_BUDGET_SHARE:.0%} of the budget); keep the methods short")


@dataclass
class RuntimeCheck:
    """A candidate to run on recorded observations in a worker (picklable)."""

    text: str
    game: str
    observations: list[tuple[int, dict[str, Any]]]
    call_time_limit_s: float = 1.0
    total_time_limit_s: float = 60.0
    memory_limit_mb: int | None = 4096


def run_check(check: RuntimeCheck, progress=None) -> str | None:
    """Runs in the worker: None if the candidate behaves on every observation, else the reason it does not."""
    try:
        policy = load_policy(check.text, "candidate.py").policy
    except PolicyLoadError as exc:
        return f"the candidate policy does not load: {exc}"
    n_actions = get_game(check.game).n_actions
    deadline = time.monotonic() + check.total_time_limit_s
    with CallTimer() as timer:
        for step, obs in check.observations:
            if time.monotonic() > deadline:
                return f"the candidate took more than {check.total_time_limit_s:g} s on {len(check.observations)} recorded steps"
            try:
                timer.arm(check.call_time_limit_s)
                try:
                    action = policy(obs)
                finally:
                    timer.disarm()
                coerce_action(action, n_actions)
            except PolicyTimeout as exc:
                return f"on the recorded observation of step {step}: {describe_exception(exc)}"
            except KeyboardInterrupt:
                raise
            except BaseException as exc:  # noqa: BLE001 - untrusted code
                return f"on the recorded observation of step {step}: {describe_exception(exc)}"
    return None


def check_at_runtime(check: RuntimeCheck) -> None:
    """Run :func:`run_check` in a hardened worker; raise :class:`CandidateRejected` with the reason."""
    [(_, reason)] = list(run_tasks(
        run_check, [check], workers=1,
        failed=lambda item, why, timed_out: f"the candidate's check crashed: {why}",
        time_limit_s=lambda item: item.total_time_limit_s,
        memory_limit_mb=lambda item: item.memory_limit_mb,
    ))
    if reason is not None:
        raise CandidateRejected(reason)


def spread(observations: list[tuple[int, dict[str, Any]]], limit: int = MAX_VALIDATION_STEPS):
    """At most ``limit`` observations, evenly spread, the first and last always included."""
    if len(observations) <= limit:
        return observations
    step = (len(observations) - 1) / (limit - 1)
    return [observations[round(i * step)] for i in range(limit)]
