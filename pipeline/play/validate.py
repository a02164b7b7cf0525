"""Validation of a candidate policy proposed by the LLM, before it becomes a policy version.

Static checks: every suggested method exists and is trainable; its source is one ``def`` of the same name with
the same parameters; it passes the sandbox's source check; spliced into the policy file, the whole file still
checks, and fits half of the prompt's token budget (:func:`check_fits`). Even parsing untrusted text can crash a
process (a 200 KB ``1 + 1 + ...`` expression exhausts the recursion limit, 100,000 unary minuses take
gigabytes, and 400 of them parse but then exhaust the recursion limit in radon's metrics), so the checks and the
code metrics run first in a confined worker (:func:`vet_here`, with a lower recursion limit than this process
has and its memory capped) and only text that passed there is parsed and measured here; a worker that dies or
hangs rejects the candidate (:func:`checked_inspect` does the same for a policy file given to ``codearcade
eval`` or ``optimize``). Then a runtime check in a confined worker process (``pipeline/boundary/workers.py``):
the candidate policy is loaded and called on observations recorded in the store (the training rollout's),
each call within the time limit and returning a legal action. The first failure rejects the candidate with a
reason that names the method, the error and, for runtime failures, the step whose observation broke it; the
reason (capped and scrubbed of secrets, ``pipeline/boundary/untrusted.py``) becomes part of the next feedback.
"""

from __future__ import annotations

import ast
import hashlib
import json
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable

from games import get_game
from pipeline.boundary.untrusted import clean_untrusted_text
from pipeline.boundary.workers import run_json_tasks
from pipeline.boundary.zygotes import start_zygotes
from pipeline.boundary.policy import coerce_action, describe_exception
from pipeline.settings import EpisodeLimits
from tracing.metrics import function_metrics, policy_metrics
from tracing.policy_file import PolicyInfo, PolicyLoadError, inspect_policy, load_policy, replace_methods
from tracing.sandbox import CallTimer, PolicyCodeError, PolicyTimeout, check_source

MAX_VALIDATION_STEPS = 200
"""Recorded observations a candidate is run on (evenly spread over the rollout)."""


def resolve_game(declared: str | None, requested: str | None, source: str) -> str:
    """The game to play, from ``--game`` and the policy's ``GAME``; errors say how to fix a mismatch."""
    if requested is None and declared is None:
        raise PolicyLoadError(f"{source} does not declare GAME = '...'; pass --game (`codearcade games` lists them)")
    if requested is not None and declared is not None and get_game(requested) != get_game(declared):
        raise PolicyLoadError(f"{source} declares GAME = '{declared}' but --game is '{requested}'; drop one of them")
    return get_game(requested or declared).name


class CandidateRejected(Exception):
    """A candidate that must not become a policy version; ``str()`` is the reason, cleaned as untrusted text
    (``pipeline/boundary/untrusted.py``: capped, secrets redacted): it quotes the candidate's own exceptions and names."""

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


VET_TIME_LIMIT_S = 20.0
"""How long the static checks of one text may take in their worker."""
RECURSION_MARGIN = 300
"""Frames fewer the vetting worker may use than this process: text it parses, this process parses too."""
_PARSE_ERRORS = (RecursionError, MemoryError, ValueError, OverflowError)


def vet_here(item: dict[str, Any]) -> str | None:
    """In a worker: the static checks of ``item`` (``op`` ``inspect``: a policy file; ``candidate``: a
    suggestion for a policy); None if they pass, else the reason. They run with a lower recursion limit."""
    before = sys.getrecursionlimit()
    sys.setrecursionlimit(max(100, int(item.get("recursion_limit", 1000)) - RECURSION_MARGIN))
    try:
        if item["op"] == "inspect":
            try:
                measure(inspect_policy(item["text"], item["name"]))
            except PolicyLoadError as exc:
                return str(exc)
        else:
            try:
                candidate = _build_candidate(inspect_policy(item["text"], item["name"]), item["suggestion"])
            except CandidateRejected as exc:
                return str(exc)
            if candidate is not None:
                measure(candidate.info)
    except _PARSE_ERRORS as exc:
        return f"the code cannot be checked ({type(exc).__name__}: too large or too deeply nested)"
    finally:
        sys.setrecursionlimit(before)  # with workers=0 this is the optimizer's own process
    return None


def vet_and_check_here(item: dict[str, Any]) -> dict[str, str | None]:
    """In a worker: :func:`vet_here`; if it passes and ``item`` carries a ``check``, :func:`check_here` on it too.
    ``reason``: the static checks' verdict; ``runtime``: the runtime check's, when it ran."""
    reason = vet_here(item)
    if reason is not None or item.get("check") is None:
        return {"reason": reason}
    return {"reason": None, "runtime": check_here(item["check"])["reason"]}


_passed: set[str] = set()
"""Digests of items that passed vetting (with this process's recursion limit): no worker for them again."""
NOT_RUN = object()
"""What :func:`_vet_all` says of a runtime check it did not run."""
_ran_clean: set[str] = set()
"""Digests of runtime checks that passed (the same code on the same observations with the same limits): best-of-n
often gets the same code twice from one prompt. Failures are not kept: a time limit depends on the load."""


def _check_digest(check: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(check, sort_keys=True).encode()).hexdigest()


def _vet(item: dict[str, Any], workers: int = 1, check: "RuntimeCheck | None" = None) -> tuple[str | None, Any]:
    """(why the static checks of ``item`` fail, or None; and the reason of ``check``, run in the same worker
    after them, or None if it passed — :data:`NOT_RUN` when the worker did not run it)."""
    return _vet_all([(item, check)], workers)[0]


def _vet_all(requests: list[tuple[dict[str, Any], "RuntimeCheck | None"]], workers: int) -> list[tuple[str | None, Any]]:
    """:func:`_vet` of each ``(item, check)``, in up to ``workers`` workers at once."""
    results: list[Any] = [None] * len(requests)
    to_run = []
    for i, (item, check) in enumerate(requests):
        vetted = {**item, "recursion_limit": sys.getrecursionlimit()}
        digest = hashlib.sha256(json.dumps(vetted, sort_keys=True).encode()).hexdigest()
        if digest in _passed:
            results[i] = (None, NOT_RUN)
            continue
        if check is not None:
            vetted["check"] = vars(check).copy()  # not asdict(): it deep-copies the observations only to send them
        to_run.append((i, digest, vetted))

    def limits(vetted: dict[str, Any]) -> tuple[float, int | None]:
        check = vetted.get("check")
        if check is None:
            return VET_TIME_LIMIT_S, 2048
        memory_mb = None if check["memory_limit_mb"] is None else max(2048, check["memory_limit_mb"])
        return VET_TIME_LIMIT_S + check["total_time_limit_s"], memory_mb

    answers = run_json_tasks("vet", [vetted for _, _, vetted in to_run], vet_and_check_here,
                             time_limit_s=lambda vetted: limits(vetted)[0], memory_mb=lambda vetted: limits(vetted)[1],
                             workers=workers)
    for (i, digest, vetted), (answered, answer) in zip(to_run, answers):
        item, check = requests[i]
        if not answered and check is not None:  # the static checks or the candidate's run? vet alone to tell
            reason, _ = _vet(item, workers)
            results[i] = (reason, NOT_RUN) if reason is not None else (None, f"the candidate's check crashed: {answer}")
        elif not answered:
            results[i] = (f"the static check of the code crashed ({answer})", NOT_RUN)
        elif answer.get("reason") is not None:
            results[i] = (answer["reason"], NOT_RUN)
        else:
            _passed.add(digest)
            results[i] = (None, answer["runtime"] if "runtime" in answer else NOT_RUN)
            if "runtime" in answer and answer["runtime"] is None:
                _ran_clean.add(_check_digest(vetted["check"]))
    return results


def measure(info: PolicyInfo) -> None:
    """Compute the code metrics that this process stores with a policy version (``pipeline/play/versions.py``; they
    are cached). radon's visitors recurse deeper than the parse does: 400 nested unary minuses parse, then
    exhaust the recursion limit in radon, so vetting computes them too."""
    for method in info.methods:
        function_metrics(method.source)
    policy_metrics(info.text)


def checked_inspect(text: str, name: str, workers: int = 1) -> PolicyInfo:
    """:func:`inspect_policy` of untrusted text (a policy file given to ``eval`` or ``optimize``), parsed and
    measured (:func:`measure`) in a confined worker first (``workers=0``: only here). Raises
    :class:`PolicyLoadError` with one line for text that cannot be checked: too large or too deeply nested
    for a parser or radon (the worker's recursion limit is lower than this process's, its memory capped).
    Every caller plays the policy next: its game zygote starts beside the policy zygote that checks it."""
    if workers > 0:
        start_zygotes("policy", "game")
        reason, _ = _vet({"op": "inspect", "text": text, "name": name})
        if reason is not None:
            raise PolicyLoadError(reason if reason.startswith(name) else f"{name}: {reason}")
    try:
        info = inspect_policy(text, name)
        measure(info)
        return info
    except _PARSE_ERRORS as exc:
        raise PolicyLoadError(f"{name}: the code cannot be checked ({type(exc).__name__})") from None


def build_candidate(info: PolicyInfo, suggestion: dict[str, str]) -> Candidate | None:
    """The candidate policy text for ``suggestion`` (static checks, vetted in a confined worker first), or
    None if it changes nothing."""
    _check_types(suggestion)
    (reason, _), = _vet_all([(_vet_item(info, suggestion), None)], workers=1)
    return _vetted_candidate(info, suggestion, reason)


Proposed = tuple[PolicyInfo, dict[str, str], Callable[[str], "RuntimeCheck"], Callable[[Candidate], None]]
"""A suggestion to validate: the policy it changes, the suggestion, its runtime check (the candidate's text ->
its :class:`RuntimeCheck`) and the check that it fits (raises :class:`CandidateRejected`)."""


def validate_candidate(info: PolicyInfo, suggestion: dict[str, str], check: Callable[[str], "RuntimeCheck"],
                       fits: Callable[[Candidate], None] = lambda candidate: None) -> tuple[Candidate | None, str | None]:
    """Every check of a suggestion, in order: the static checks (:func:`build_candidate`), ``fits`` (raises
    :class:`CandidateRejected` too), then the runtime check (``check``: the candidate's text -> its
    :class:`RuntimeCheck`). Returns (None, None) if the suggestion changes nothing, else the candidate and the
    runtime check's reason to reject it (None: it passed; cleaned as untrusted text).

    One worker round trip instead of two: the candidate's text is spliced into the (trusted) policy without
    parsing the suggestion here, and the vetting worker runs the runtime check on it right after the static
    checks. This process still parses nothing the worker has not vetted; if what it then builds differs from
    the spliced text (it cannot, short of a bug), the runtime check runs again on what was built."""
    (result,) = validate_candidates([(info, suggestion, check, fits)], workers=1)
    if isinstance(result, CandidateRejected):
        raise result
    return result


def validate_candidates(proposed: list[Proposed], workers: int = 1) -> list[tuple[Candidate | None, str | None] | CandidateRejected]:
    """:func:`validate_candidate` of each, with up to ``workers`` worker round trips at once (an iteration of
    best-of-n validates N); each result is what it returns or the :class:`CandidateRejected` it raises."""
    results: list[Any] = [None] * len(proposed)
    requests, asked = [], []
    for i, (info, suggestion, check, _) in enumerate(proposed):
        try:
            _check_types(suggestion)
        except CandidateRejected as exc:
            results[i] = exc
            continue
        spliced = _spliced(info, suggestion)
        requests.append((_vet_item(info, suggestion), check(spliced) if spliced is not None else None))
        asked.append((i, spliced))
    rerun = []
    for (i, spliced), (reason, runtime) in zip(asked, _vet_all(requests, workers)):
        info, suggestion, check, fits = proposed[i]
        try:
            candidate = _vetted_candidate(info, suggestion, reason)
            if candidate is not None:
                fits(candidate)
        except CandidateRejected as exc:
            results[i] = exc
            continue
        results[i] = (candidate, runtime)
        if candidate is not None and (runtime is NOT_RUN or candidate.text != spliced):
            rerun.append(i)
    checks = [proposed[i][2](results[i][0].text) for i in rerun]
    for i, runtime in zip(rerun, _runtime_reasons(checks, workers)):
        results[i] = (results[i][0], runtime)
    for i, result in enumerate(results):
        if isinstance(result, tuple) and result[1] is not None:  # cleaned as a CandidateRejected's reason is
            results[i] = (result[0], clean_untrusted_text(result[1]))
    return results


def _check_types(suggestion: dict[str, str]) -> None:
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in suggestion.items()):
        raise CandidateRejected("the suggestion must map method names to source text")


def _vet_item(info: PolicyInfo, suggestion: dict[str, str]) -> dict[str, Any]:
    return {"op": "candidate", "text": info.text, "name": info.name, "suggestion": dict(suggestion)}


def _vetted_candidate(info: PolicyInfo, suggestion: dict[str, str], reason: str | None) -> Candidate | None:
    """Once vetting said ``reason`` (None: passed): the candidate built and measured here, or None if it changes
    nothing."""
    if reason is not None:
        raise CandidateRejected(reason)
    try:
        candidate = _build_candidate(info, suggestion)
        if candidate is not None:
            measure(candidate.info)
        return candidate
    except _PARSE_ERRORS as exc:
        raise CandidateRejected(f"the code cannot be checked ({type(exc).__name__})") from None


def _spliced(info: PolicyInfo, suggestion: dict[str, str]) -> str | None:
    """The text :func:`_build_candidate` makes of ``suggestion`` when its static checks pass, made without
    parsing the suggestion (whose types :func:`_check_types` checked); None when it changes nothing or names a
    method that may not change."""
    methods = {m.name: m for m in info.methods}
    if not all(name in methods and methods[name].trainable for name in suggestion):
        return None
    changed = _changed_sources(methods, suggestion)
    return replace_methods(info.text, changed) if changed else None


def _changed_sources(methods: dict[str, Any], suggestion: dict[str, str]) -> dict[str, str]:
    """The suggested sources that differ from the methods' (both the spliced and the built text use these)."""
    return {name: source for name, source in suggestion.items() if source.strip() != methods[name].source.strip()}


def _build_candidate(info: PolicyInfo, suggestion: dict[str, str]) -> Candidate | None:
    methods = {m.name: m for m in info.methods}
    trainable = [m.name for m in info.trainable]
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
    changed = _changed_sources(methods, suggestion)
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
    """A candidate to run on recorded observations in a worker (sent as JSON)."""

    text: str
    game: str
    observations: list[tuple[int, dict[str, Any]]]
    n_actions: int | None = None
    """The game's number of actions (None: looked up here; a policy process cannot look up a generic game: it
    cannot read OCAtari's files)."""
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s
    total_time_limit_s: float = 60.0
    memory_limit_mb: int | None = EpisodeLimits.memory_limit_mb


def run_check(check: RuntimeCheck, progress=None) -> str | None:
    """Runs in the worker: None if the candidate behaves on every observation, else the reason it does not."""
    try:
        policy = load_policy(check.text, "candidate.py").policy
    except PolicyLoadError as exc:
        return f"the candidate policy does not load: {exc}"
    n_actions = check.n_actions if check.n_actions is not None else get_game(check.game).n_actions
    deadline = time.monotonic() + check.total_time_limit_s
    with CallTimer() as timer:
        for step, obs in check.observations:
            if time.monotonic() > deadline:
                return f"the candidate took more than {check.total_time_limit_s:g} s on {len(check.observations)} recorded steps"
            try:
                coerce_action(timer.call(check.call_time_limit_s, policy, obs), n_actions)
            except PolicyTimeout as exc:
                return f"on the recorded observation of step {step}: {describe_exception(exc)}"
            except KeyboardInterrupt:
                raise
            except BaseException as exc:  # noqa: BLE001 - untrusted code
                return f"on the recorded observation of step {step}: {describe_exception(exc)}"
    return None


def check_here(item: dict[str, Any]) -> dict[str, str | None]:
    """In a worker: :func:`run_check` of a :class:`RuntimeCheck` sent as JSON."""
    item = {**item, "observations": [(int(step), obs) for step, obs in item["observations"]]}
    return {"reason": run_check(RuntimeCheck(**item))}


def check_at_runtime(check: RuntimeCheck) -> None:
    """Run :func:`run_check` in a confined worker; raise :class:`CandidateRejected` with the reason."""
    (reason,) = _runtime_reasons([check], workers=1)
    if reason is not None:
        raise CandidateRejected(reason)


def _runtime_reasons(checks: list[RuntimeCheck], workers: int) -> list[str | None]:
    """The reason each check fails (None: passed), in up to ``workers`` workers at once."""
    items = [vars(c).copy() for c in checks]  # not asdict(): see _vet_all
    digests = [_check_digest(item) for item in items]
    to_run = [i for i, digest in enumerate(digests) if digest not in _ran_clean]
    answers = run_json_tasks("check", [items[i] for i in to_run], check_here,
                             time_limit_s=lambda item: item["total_time_limit_s"],
                             memory_mb=lambda item: item["memory_limit_mb"], workers=workers)
    reasons: list[str | None] = [None] * len(checks)
    for i, (answered, answer) in zip(to_run, answers):
        reasons[i] = answer["reason"] if answered else f"the candidate's check crashed: {answer}"
        if reasons[i] is None:
            _ran_clean.add(digests[i])
    return reasons


def spread(observations: list[tuple[int, dict[str, Any]]], limit: int = MAX_VALIDATION_STEPS):
    """At most ``limit`` observations, evenly spread, the first and last always included."""
    if len(observations) <= limit:
        return observations
    step = (len(observations) - 1) / (limit - 1)
    return [observations[round(i * step)] for i in range(limit)]
