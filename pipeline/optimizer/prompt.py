"""The optimizer's prompt, rendered from slices of the store under a hard token budget.

The sections follow OptoPrime's (#Instruction, #Code, #Documentation, #Variables, #Constraints, #Inputs,
#Others, #Outputs, #Feedback) plus #Memory, the last k iterations. Everything comes from the store
(``pipeline/optimizer/context.py`` reads it into a :class:`PromptContext`): the policy text of the version being improved, the traced training rollout (steps
and node calls), the evaluation episodes, the feedback, and earlier iterations.

Budget: the fixed sections (instruction, code, variables, constraints, feedback, summaries) must fit, or
:class:`PromptBudgetError` says how much is needed. Memory entries are added newest first (with their code
diff when it fits, else just score and feedback). Then steps of the training rollout are added by priority:
the steps before each lost point or life (and a policy failure) first, round-robin from the event backwards,
then the first steps of the episode, then the rest evenly spread. The whole request is counted at the end and
trimmed if needed, so the prompt never exceeds the budget.

The text is deterministic (no addresses, timings or counters), so its hash identifies the call: a run can be
resumed or replayed from the store without calling the model again.
"""

from __future__ import annotations

import ast
import json
from dataclasses import dataclass
from typing import Any

from games import get_game
from pipeline.boundary.untrusted import single_line
from pipeline.llm.client import prompt_hash
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.context import VALUE_CHARS, PromptContext
from pipeline.optimizer.strategies import format_number
from store.held_values import JsonHead
from tracing.line_diff import unified_diff as bounded_unified_diff
from tracing.policy_file import TASK_CONSTANTS, PolicyInfo, replace_methods
from tracing.sandbox import ALLOWED_MODULES

EVENT_WINDOW = 30
"""Steps shown before each lost point/life (about one ball crossing in Pong)."""
MAX_VALUE_CHARS = VALUE_CHARS
"""Characters of a node value shown (the context reads no more of it from the store: ``context.VALUE_CHARS``)."""

SYSTEM = """You improve a game-playing policy written in Python. The policy is a class; some of its methods are \
trainable and you may rewrite them. The request has these sections:
#Instruction: what to achieve.
#Code: the policy file, with each trainable method shown as a stub (its code is in #Variables).
#Documentation: what the game and the non-trainable parts do.
#Variables: the current source of each trainable method; these are what you change.
#Constraints: rules every new method must follow.
#Inputs: observations the policy received in a traced training rollout.
#Others: the intermediate values: each call of a method in those steps, with its inputs and output.
#Outputs: the actions taken and rewards received, and how the evaluation games ended.
#Feedback: how well the current policy plays, and what happened to your last suggestion.
#Memory: earlier iterations: their score, feedback, and how their code differs from the current code.

Reply with JSON only, in this form:
{"reasoning": "<your analysis of the trace and feedback>", "suggestion": {"<method name>": "<complete new \
source of the method: a def with the same name and parameters, docstring included>"}}
Include only the methods you change. If you cannot reply in JSON, give each changed method as a complete def in \
its own ```python fenced block."""


class PromptBudgetError(ValueError):
    """The mandatory part of the prompt does not fit the token budget."""


@dataclass
class Prompt:
    messages: list[dict[str, str]]
    tokens: int
    budget: int
    steps_shown: list[int]
    memory_shown: int
    token_method: str

    @property
    def hash(self) -> str:
        return prompt_hash(self.messages)


# ---------------------------------------------------------------------------------------------- rendering


def _value(value: Any) -> str:
    if isinstance(value, JsonHead):  # the start of a stored value's compact JSON: what json.dumps would print
        return value.text if value.length <= MAX_VALUE_CHARS else value.text[:MAX_VALUE_CHARS] + "…"
    if value == {"$ref": "obs"}:
        return "obs"
    if isinstance(value, float):
        return format_number(value)
    text = json.dumps(value, separators=(",", ":")) if not isinstance(value, str) else json.dumps(value)
    return text if len(text) <= MAX_VALUE_CHARS else text[:MAX_VALUE_CHARS] + "…"


_BOX = ("x", "y", "w", "h", "dx", "dy")


def _is_object(value: Any) -> bool:
    return isinstance(value, dict) and all(f in value for f in _BOX)


def _extra(value: Any) -> str:
    return value if isinstance(value, str) else _value(value)


def _obj(o: dict[str, Any]) -> str:
    """``(x,y,w,h,dx,dy)``, then the fields a game's ``derive`` added: ``(26,42,8,11,0,0,type=Enemy,lane=1)``."""
    box = f"{o['x']},{o['y']},{o['w']},{o['h']},{o['dx']},{o['dy']}"
    extra = ",".join(f"{k}={_extra(v)}" for k, v in o.items() if k not in _BOX)
    return f"({box},{extra})" if extra else f"({box})"


def render_obs(obs: dict[str, Any]) -> str:
    """Compact observation text: ``Ball(x,y,w,h,dx,dy)``; lists as ``RB[n] y=.. w=.. h=.. x=..`` when uniform;
    derived values that are not objects (``lives``, ``enemy_lanes``) as ``key=value``."""
    parts = []
    for key, value in obs.items():
        if isinstance(value, list) and all(_is_object(o) for o in value):
            if not value:
                parts.append(f"{key}[0]")
            elif all(len(o) == len(_BOX) for o in value) and \
                    len({(o["y"], o["w"], o["h"], o["dx"], o["dy"]) for o in value}) == 1:
                first = value[0]
                xs = ",".join(str(o["x"]) for o in value)
                parts.append(f"{key}[{len(value)}] y={first['y']} w={first['w']} h={first['h']} x={xs}")
            else:
                parts.append(f"{key}[{len(value)}] " + " ".join(_obj(o) for o in value))
        elif _is_object(value):
            parts.append(key + _obj(value))
        else:
            parts.append(f"{key}={_extra(value)}")
    return " ".join(parts) if parts else "(no objects)"


def _call(node: dict[str, Any]) -> str:
    """``name(args) -> output`` (or the exception) of one node call; rendered once per node row (rows of a
    rollout are kept across prompts, see ``context._rollout``)."""
    text = node.get("_rendered")
    if text is None:
        text = node["_rendered"] = _render_call(node)
    return text


def _render_call(node: dict[str, Any]) -> str:
    inputs = node["inputs"] or {}
    if isinstance(inputs, dict):
        args = ", ".join(("obs" if k == "obs" and v == {"$ref": "obs"} else f"{k}={_value(v)}")
                         for k, v in inputs.items())
    else:  # a marker for inputs too deep or too long (tracing/bounded.py), or a store edited by hand
        args = _value(inputs)
    head = f"{node['function']}({args})"
    if node["exc_type"]:  # the exception's texts are the policy's: one line each, so no line of theirs is a header
        line = f" at line {node['exc_line']}: {single_line(node['exc_source'])}" if node["exc_source"] else ""
        return f"{head} raised {single_line(node['exc_type'])}: {single_line(node['exc_message'] or '')}{line}"
    return f"{head} -> {_value(node['output'])}"


def code_view(info: PolicyInfo) -> str:
    """The policy file with task constants removed and each trainable method reduced to a stub."""
    stubs = {}
    for m in info.trainable:
        node = ast.parse(m.source).body[0]
        signature = f"def {m.name}({ast.unparse(node.args)}):"
        stubs[m.name] = f"{signature}\n    ...  # trainable: its current code is in #Variables\n"
    text = replace_methods(info.text, stubs) if stubs else info.text
    tree = ast.parse(text)
    drop: set[int] = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id in TASK_CONSTANTS for t in node.targets):
            drop.update(range(node.lineno - 1, node.end_lineno))
        elif node is tree.body[0] and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            drop.update(range(node.lineno - 1, node.end_lineno))  # the module docstring is for humans
    lines = [line for i, line in enumerate(text.splitlines()) if i not in drop]
    out: list[str] = []
    for line in lines:  # collapse the blank runs left behind
        if line.strip() or (out and out[-1].strip()):
            out.append(line)
    return "\n".join(out).strip() + "\n"


def _documentation(ctx: PromptContext) -> str:
    game = get_game(ctx.game)
    actions = ", ".join(f"{i} {name}" for i, name in enumerate(game.actions))
    lines = [f"Game: {game.name} ({game.env_id}, frameskip 4). Actions: {actions}."]
    lines.append("Observations are dicts of objects; each object is written Name(x, y, w, h, dx, dy): position "
                 "of the top-left corner, size, and movement since the previous step (y grows downward). "
                 "An object that is not on screen is absent.")
    tree = ast.parse(ctx.info.text)
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == "Policy" and ast.get_docstring(node):
            lines.append("Policy: " + ast.get_docstring(node))
    for m in ctx.info.methods:
        if not m.trainable:
            doc = ast.get_docstring(ast.parse(m.source).body[0])
            if doc:
                lines.append(f"{m.name}: {doc}")
    return "\n".join(lines)


def _constraints(ctx: PromptContext) -> str:
    game = get_game(ctx.game)
    names = ", ".join(m.name for m in ctx.info.trainable)
    allowed = ", ".join(sorted(ALLOWED_MODULES - {"__future__", "tracing"}))
    return (
        f"- Change only the trainable methods ({names}); keep each method's name and parameters exactly.\n"
        f"- The policy must return an int action in 0..{game.n_actions - 1} for every observation, including "
        "observations where objects are missing.\n"
        f"- Imports allowed: {allowed}. No files, network, processes, eval/exec, dunder attributes, or "
        "`except:`/`except BaseException`.\n"
        f"- One call of the policy must finish within {ctx.call_time_limit_s:g} s."
    )


def _diff(old: dict[str, str], new: dict[str, str]) -> str:
    """A memory entry's methods against the current version's, one unified diff per method that differs, matched
    at a cost bounded by their length (``tracing/line_diff.py``): both come from replies, and difflib's matcher
    took 2.7 s a prompt on two methods built for it (20 s within a 32k budget), with the store held. The same text
    as ``difflib.unified_diff`` gives for every method a model writes (under 200 lines)."""
    lines: list[str] = []
    for name in sorted(set(old) | set(new)):
        a, b = old.get(name, "").splitlines(), new.get(name, "").splitlines()
        if a != b:
            lines.extend(line.rstrip("\n") for line in bounded_unified_diff(
                a, b, f"iteration version: {name}", f"current version: {name}", context=1))
    return "\n".join(lines)


def _events(steps: list[dict[str, Any]], game_has_lives: bool) -> list[tuple[int, str]]:
    events = []
    for i, row in enumerate(steps):
        if row["action"] is None:
            events.append((row["step"], "policy failed"))
        elif row["reward"] < 0:
            events.append((row["step"], "point lost"))
        elif game_has_lives and i + 1 < len(steps) and (steps[i + 1]["lives"] or 0) < (row["lives"] or 0):
            events.append((row["step"], "life lost"))
    return events


def _priority(steps: list[dict[str, Any]], events: list[tuple[int, str]]) -> list[int]:
    """Step indices in the order they are worth showing (see the module docstring)."""
    n = len(steps)
    index_of = {row["step"]: i for i, row in enumerate(steps)}
    order: list[int] = []
    seen: set[int] = set()

    def add(i: int) -> None:
        if 0 <= i < n and i not in seen:
            seen.add(i)
            order.append(i)

    event_indices = [index_of[s] for s, _ in events if s in index_of]
    for distance in range(EVENT_WINDOW):
        for e in event_indices:
            add(e - distance)
    for i in range(min(n, EVENT_WINDOW)):
        add(i)
    remaining = [i for i in range(n) if i not in seen]
    stride = 1
    while stride * 2 <= len(remaining):
        stride *= 2
    while remaining:  # coarse-to-fine spread over what is left
        for i in remaining[::stride]:
            add(i)
        remaining = [i for i in remaining if i not in seen]
        stride = max(1, stride // 2)
    return order


def _segments(steps: list[dict[str, Any]], nodes_by_step: dict[int, list[dict[str, Any]]],
              collapse: bool) -> list[list[int]]:
    """Step indices in display units: each step alone, or with ``collapse`` a run of consecutive steps whose
    calls (inputs and outputs), action and reward are the same as one unit (only the observation moves)."""
    if not collapse:
        return [[i] for i in range(len(steps))]
    units: list[list[int]] = []
    previous = None
    for i, row in enumerate(steps):
        calls = nodes_by_step.get(row["step"], [])
        signature = (tuple(_call(n) for n in calls), row["action"], row["reward"]) if calls else None
        if signature is not None and signature == previous and row["action"] is not None:
            units[-1].append(i)
        else:
            units.append([i])
        previous = signature
    return units


def _unit_lines(unit: list[int], steps: list[dict[str, Any]],
                nodes_by_step: dict[int, list[dict[str, Any]]]) -> tuple[str, str, str]:
    """The #Inputs, #Others and #Outputs lines of a display unit."""
    first = steps[unit[0]]
    if len(unit) == 1:
        return _obs_line(first), _calls_line(first, nodes_by_step), _out_line(first)
    last = steps[unit[-1]]
    span = f"steps {first['step']}-{last['step']}"
    calls = " | ".join(_call(n) for n in nodes_by_step.get(first["step"], []))
    return (f"{span} ({len(unit)} steps with the same calls and action; step {first['step']} shown): "
            f"{render_obs(first['obs'])}",
            f"{span}: {calls} (each step)",
            f"{span}: action {first['action']}, reward {format_number(first['reward'])} each, score "
            f"{format_number(last['score'])}")


# ---------------------------------------------------------------------------------------------- building


def smallest_prompt_tokens(game: str, instruction: str, info: PolicyInfo, counter: TokenCounter,
                           call_time_limit_s: float) -> int:
    """The tokens of a prompt for ``info`` before anything has played: its code, instructions and documentation,
    an empty rollout, no feedback and no memory. Every prompt of a run that starts from ``info`` needs at least
    these (what an iteration adds only adds to them), so a budget below them can be refused before iteration 0
    plays for minutes."""
    empty = PromptContext(game=game, instruction=instruction, info=info,
                          train_episode={"length": 0, "return": 0.0, "end_reason": "truncated", "error": None},
                          train_steps=[], train_nodes=[], eval_episodes=[], feedback="",
                          call_time_limit_s=call_time_limit_s)
    return build_prompt(empty, 2**31, counter).tokens


def check_prompt_fits(budget: int, game: str, instruction: str, info: PolicyInfo, model: str,
                      call_time_limit_s: float) -> None:
    """:class:`PromptBudgetError` when the policy code and instructions alone (:func:`smallest_prompt_tokens`,
    counted for ``model``) need more tokens than ``budget``: said before a run is made."""
    need = smallest_prompt_tokens(game, instruction, info, TokenCounter(model), call_time_limit_s)
    if need > budget:
        raise PromptBudgetError(f"the policy code and instructions alone need {need} tokens, more than the budget of "
                                f"{budget}; raise --token-budget (a rollout and feedback need more), or lower "
                                "--max-tokens where the model's context holds the budget")


def build_prompt(ctx: PromptContext, budget: int, counter: TokenCounter) -> Prompt:
    """Assemble the prompt for ``ctx`` within ``budget`` tokens (see the module docstring)."""
    game = get_game(ctx.game)
    steps, nodes = ctx.train_steps, ctx.train_nodes
    events = _events(steps, game.lives > 0)
    nodes_by_step: dict[int, list[dict[str, Any]]] = {}
    for node in nodes:
        nodes_by_step.setdefault(node["step"], []).append(node)

    ep = ctx.train_episode
    event_text = "; ".join(f"{what} at step {s}" for s, what in events) or "no point or life lost"
    inputs_head = (f"Training rollout of the current policy: {ep['length']} steps, return {format_number(ep['return'])}, "
                   f"ended: {ep['end_reason']}. Events: {event_text}.")
    if ep.get("error"):
        inputs_head += f"\nThe policy failed: {single_line(ep['error'])}"
    evals = ctx.eval_episodes
    outputs_tail = "Evaluation games: " + "; ".join(
        f"return {format_number(e['return'])} in {e['length']} steps ({e['end_reason']}"
        + (f": {single_line(e['error'])}" if e.get("error") else "") + ")" for e in evals
    ) if evals else "Evaluation games: none."

    variables = "\n\n".join(f"(code) {m.name}:\n```python\n{m.source.rstrip()}\n```" for m in ctx.info.trainable)
    fixed = {
        "#Instruction": ctx.instruction.strip(),
        "#Code": f"```python\n{code_view(ctx.info).rstrip()}\n```",
        "#Documentation": _documentation(ctx),
        "#Variables": variables,
        "#Constraints": _constraints(ctx),
        "#Feedback": ctx.feedback.strip() or "(no feedback yet)",
    }

    units = _segments(steps, nodes_by_step, ctx.collapse_repeats)
    unit_of = {i: u for u, members in enumerate(units) for i in members}
    lines = {}

    def unit_lines(u: int) -> tuple[str, str, str]:
        if u not in lines:
            lines[u] = _unit_lines(units[u], steps, nodes_by_step)
        return lines[u]

    def assemble(shown: list[int], memory: list[str]) -> list[dict[str, str]]:
        shown = sorted(shown)
        obs_lines, call_lines, out_lines = [], [], []
        previous = None
        for u in shown:
            first = units[u][0]
            if previous is not None and first != units[previous][-1] + 1:
                gap = f"… steps {steps[units[previous][-1]]['step'] + 1}-{steps[first]['step'] - 1} omitted"
                obs_lines.append(gap)
                call_lines.append(gap)
                out_lines.append(gap)
            obs_line, calls_line, out_line = unit_lines(u)
            obs_lines.append(obs_line)
            call_lines.append(calls_line)
            out_lines.append(out_line)
            previous = u
        covered = sum(len(units[u]) for u in shown)
        shown_note = (f"Showing {covered} of {len(steps)} steps" +
                      (" (the steps before each lost point or life first)." if covered < len(steps) else "."))
        sections = [
            ("#Instruction", fixed["#Instruction"]),
            ("#Code", fixed["#Code"]),
            ("#Documentation", fixed["#Documentation"]),
            ("#Variables", fixed["#Variables"]),
            ("#Constraints", fixed["#Constraints"]),
            ("#Inputs", "\n".join([inputs_head, shown_note] + obs_lines)),
            ("#Others", "\n".join(call_lines) if call_lines else "(no calls shown)"),
            ("#Outputs", "\n".join(out_lines + [outputs_tail])),
            ("#Feedback", fixed["#Feedback"]),
            ("#Memory", "\n\n".join(memory) if memory else "(no earlier iterations)"),
        ]
        user = "\n\n".join(f"{title}\n{body}" for title, body in sections)
        return [{"role": "system", "content": SYSTEM}, {"role": "user", "content": user}]

    base_tokens = counter.messages(assemble([], []))
    if base_tokens > budget:
        raise PromptBudgetError(
            f"the policy code, instructions and feedback alone need {base_tokens} tokens, more than the budget "
            f"of {budget}; raise --token-budget")
    used = base_tokens

    memory_texts: list[str] = []
    current = {m.name: m.source for m in ctx.info.trainable}
    for entry in ctx.memory:  # newest first
        head = (f"Iteration {entry.iteration}: score {format_number(entry.score) if entry.score is not None else 'none (a game forfeited)'}, "
                f"update {entry.update_status}.\nFeedback: {entry.feedback.strip()}")
        diff = _diff(entry.sources, current)
        full = head + ("\nCode differences from the current version:\n```diff\n" + diff + "\n```" if diff
                       else "\nSame code as the current version.")
        for text in (full, head):
            cost = counter(text) + 2
            if used + cost <= budget:
                memory_texts.append(text)
                used += cost
                break
        else:
            break

    shown: list[int] = []  # display units
    considered: set[int] = set()
    for i in _priority(steps, events):
        u = unit_of[i]
        if u in considered:
            continue
        considered.add(u)
        cost = sum(counter(line) for line in unit_lines(u)) + 3
        if used + cost > budget:
            continue  # a shorter step further down the list may still fit
        shown.append(u)
        used += cost

    # Gap markers and joins can tip it over: keep the longest prefix of the chosen units that fits (the first
    # that fits, counting down from all of them). Counting a whole prompt is the expensive part, so the search
    # steps down 1, 2, 4, ... units, then scans down the last step, which finds the same prefix as going one
    # unit at a time.
    def fits(k: int) -> tuple[list[dict[str, str]], int] | None:
        candidate = assemble(shown[:k], memory_texts)
        count = counter.messages(candidate)
        return (candidate, count) if count <= budget else None

    messages = assemble(shown, memory_texts)
    tokens = counter.messages(messages)
    if tokens > budget and shown:
        n, step, failed, found = len(shown), 1, len(shown), None
        while found is None and failed > 0:
            k = max(0, n - step)
            found = fits(k)
            if found is None:
                failed, step = k, step * 2
            elif k + 1 < failed:  # something between k and the last failure may fit: scan it downwards
                for j in range(failed - 1, k, -1):
                    better = fits(j)
                    if better is not None:
                        found, k = better, j
                        break
        if found is not None:
            shown = shown[:k]
            messages, tokens = found
        else:
            shown = []
            messages = assemble(shown, memory_texts)
            tokens = counter.messages(messages)
    while tokens > budget and memory_texts:
        memory_texts.pop()
        messages = assemble(shown, memory_texts)
        tokens = counter.messages(messages)
    return Prompt(messages, tokens, budget, sorted(steps[i]["step"] for u in shown for i in units[u]),
                  len(memory_texts), counter.method)


def _obs_line(row: dict[str, Any]) -> str:
    text = row.get("_rendered")
    if text is None:  # once per step row (rows of a rollout are kept across prompts, see context._rollout)
        text = row["_rendered"] = f"step {row['step']}: {render_obs(row['obs'])}"
    return text


def _calls_line(row: dict[str, Any], nodes_by_step: dict[int, list[dict[str, Any]]]) -> str:
    calls = nodes_by_step.get(row["step"], [])
    return f"step {row['step']}: " + (" | ".join(_call(n) for n in calls) if calls else "(no calls recorded)")


def _out_line(row: dict[str, Any]) -> str:
    if row["action"] is None:
        return f"step {row['step']}: no action (the policy failed)"
    return f"step {row['step']}: action {row['action']}, reward {format_number(row['reward'])}, score {format_number(row['score'])}"


def trace_slice(steps: list[dict[str, Any]], nodes: list[dict[str, Any]], game_has_lives: bool,
                limit: int) -> tuple[list[tuple[int, str]], list[dict[str, Any]]]:
    """The prompt's choice of steps, for a reader outside the prompt (``codearcade serve``'s feedback): the
    rollout's events and, in step order, the ``limit`` steps a prompt shows first (the steps before each lost point or life and a policy failure, then the
    first steps, then the rest spread), each as its observation, calls and outcome lines, as #Inputs, #Others and
    #Outputs write them."""
    nodes_by_step: dict[int, list[dict[str, Any]]] = {}
    for node in nodes:
        nodes_by_step.setdefault(node["step"], []).append(node)
    events = _events(steps, game_has_lives)
    chosen = sorted(_priority(steps, events)[:max(0, limit)])
    return events, [{"step": steps[i]["step"], "observation": _obs_line(steps[i]),
                     "calls": _calls_line(steps[i], nodes_by_step), "outcome": _out_line(steps[i])} for i in chosen]
