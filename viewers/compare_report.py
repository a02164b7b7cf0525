"""What ``codearcade compare`` shows: the learning-curves plot, the terminal text and the Markdown report.

Input is the plain data of :mod:`pipeline.play.versus` (``RunComparison.as_dict()`` / ``VersionComparison.as_dict()``).
The plot draws both runs' score and best-so-far against the three budgets a run spends (LLM calls, tokens,
wall seconds), one panel each, with matplotlib's Agg canvas (no display needed); A wide and solid under B narrow and
dashed, A's dots filled inside B's hollow squares, so neither hides the other where they coincide.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from store.runs import shortest_prefixes
from store.scores import PLAYED_OUT, score_text
from store.statistics import MEAN_METHOD, interval_text
from viewers.report import _md_table
from viewers.report_figures import fitted_layout, save_png
from viewers.safe_text import markdown_code, markdown_code_block, markdown_text, plot_text, terminal_text
from viewers.tables import format_table
from viewers.whole_files import writing

COLOURS = {"A": "#1f77b4", "B": "#d62728"}
LINES = {  # where the two curves coincide, A's wide solid line shows on both sides of B's narrow dashed one
    "A": {"linestyle": "-", "linewidth": 3.2, "alpha": 0.55, "zorder": 2},
    "B": {"linestyle": (0, (4, 2)), "linewidth": 1.5, "alpha": 1.0, "zorder": 3},
}
DOTS = {  # and A's filled dots show inside B's hollow squares
    "A": {"marker": "o", "s": 16, "zorder": 4},
    "B": {"marker": "s", "s": 46, "facecolors": "none", "linewidths": 1.1, "zorder": 5},
}
PANELS = (("llm_calls", "LLM calls", 1.0), ("tokens", "tokens (thousands)", 1000.0), ("elapsed_s", "wall seconds", 1.0))


def curves_figure(data: dict[str, Any]):
    """Both runs' learning curves on one figure: score (dots) and best so far (steps) per LLM call, per thousand
    tokens and per wall second."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.2), dpi=110, layout=fitted_layout())
    axes = fig.subplots(1, len(PANELS), sharey=True)
    short = shortest_prefixes(run["run_id"] for run in data["runs"])
    for ax, (key, xlabel, scale) in zip(axes, PANELS):
        ax.grid(True, alpha=0.3)
        ax.spines[["top", "right"]].set_visible(False)
        for run in data["runs"]:
            label = run["label"]
            curve = data["curves"][label]
            xs = [p[key] / scale for p in curve]
            colour = COLOURS[label]
            ax.step(xs, [p["best_score"] for p in curve], where="post", color=colour, **LINES[label],
                    label=f"{label} {short[run['run_id']]} best so far")
            dots = DOTS[label]
            ax.scatter(xs, [p["score"] for p in curve], **({"edgecolors": colour} if "facecolors" in dots
                                                          else {"color": colour, "linewidths": 0}),
                       **dots, label=f"{label} score of an iteration")
        ax.set_xlabel(xlabel)
    from matplotlib.ticker import MaxNLocator

    axes[0].xaxis.set_major_locator(MaxNLocator(integer=True))  # whole LLM calls
    axes[0].set_ylabel("evaluation score")
    axes[-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    runs = data["runs"]
    title = fig.suptitle(plot_text(f"{data['game']}: A {runs[0]['run_id']} ({runs[0]['model']}) vs B "
                                   f"{runs[1]['run_id']} ({runs[1]['model']})"), fontsize=10, wrap=True)
    fig.get_layout_engine().fit(title)  # inside the figure: at its spaces, a long name between its characters
    return fig


def _score(value: Any) -> str:
    return "-" if value is None else score_text(value)


def _best(run: dict[str, Any]) -> str:
    """A run's best score with its interval, level, method and n, ``12.0 [10.5, 13.5] 95% t, n=3``; the value and
    why without one (``store.statistics.interval_text``)."""
    if run["best_score"] is None:  # no score: the best (the starter, when every candidate forfeited) forfeited
        return "no score (forfeited)" if run.get("best_forfeited") else _score(run["best_score"])
    return interval_text(run["best_score"], run.get("best_low"), run.get("best_high"), run["best_episodes"],
                         MEAN_METHOD) + (" by validation" if run.get("best_by") == "validation" else "")


def _held_out(run: dict[str, Any]) -> str:
    """A run's best on its held-out audit games (``codearcade audit``): its score with its interval, ``no score
    (forfeited)``, or ``-`` when it has none (never audited, or its audit played an earlier best)."""
    held = run.get("held_out")
    if held is None:
        return "-"
    if held["score"] is None:
        return "no score (forfeited)"
    return interval_text(held["mean"], held["low"], held["high"], held["played"], MEAN_METHOD, reason=held["reason"])


def _best_difference(data: dict[str, Any]) -> str:
    """Whether the two runs' bests differ beyond the noise, in words: on their held-out audit games when both have
    them, with the tuning figures beside; else the tuning figures, not tested, and the audits that would test them
    (or why they cannot be compared: a best that forfeited a game has no score), with the sensitivity line."""
    found = data["difference"]
    sensitivity = (found.get("sensitivity") or {}).get("text")
    tail = f"; {sensitivity}" if sensitivity else ""
    if found.get("basis") == "held_out":
        games = " and ".join(str(len(r["held_out"]["seeds"])) for r in data["runs"])
        counts = " and ".join(f"{r['best_episodes']}" for r in data["runs"])
        tuning = found["tuning"]
        # a finalized served run's best was picked on its validation games, an optimization's on its tuning episodes
        picked_on = {"validation games" if r.get("best_by") == "validation" else "tuning episodes"
                     for r in data["runs"]}
        beside = (f"; on the {' and '.join(sorted(picked_on))} that picked them ({counts}): "
                  f"A - B = {tuning['interval']}, "
                  f"{tuning['note']}" if tuning.get("interval") else "")
        return (f"best versions, held out (the standard protocol on their sealed audit games, {games}): "
                f"{found['verdict']}{tail}{beside}")
    counts = " and ".join(f"{r['best_episodes']}" for r in data["runs"])
    commands = found.get("audit_commands") or []
    notes = ([f"to test it: {', '.join(f'`{c}`' for c in commands)}"] if commands else []) \
        + ([RUNS_PAPER_NOTE] if any(r.get("best_protocol") == "deterministic" for r in data["runs"]) else [])
    return (f"best versions, over their evaluation episodes ({counts}): {found['verdict']}{tail}"
            + "".join(f" ({note})" for note in notes))


RUNS_PAPER_NOTE = ("under the paper's protocol each episode replays the same game, so the interval measures only the "
                   "policies' own random draws; `codearcade compare A:best B:best --audit` plays both on sealed audit "
                   "seeds under the standard protocol")


def _amount(value: float) -> str:
    """A budget for people, as ``budget_table`` rounded it (three decimals), without trailing zeros: two budgets
    are two rows however close (3.08 and 3.12 wall seconds, 0.007 and 0.013 thousand tokens; to two decimals the
    latter both read 0.01)."""
    return f"{value:.3f}".rstrip("0").rstrip(".")


def _budget_rows(data: dict[str, Any]) -> list[tuple]:
    rows = []
    for r in data["budgets"]:
        budget = r["budget"]
        if budget == "all":
            budget = f"all (A {_amount(r['spent']['A'])}, B {_amount(r['spent']['B'])})"
        else:
            budget = _amount(budget)
        rows.append((r["unit"], budget, _score(r["A"]), _score(r["B"])))
    return rows


def _obs_text(obs: dict[str, Any], limit: int = 6) -> str:
    """Objects of an observation as ``Ball(80,120 d+2,-1)``; the first ``limit`` of them."""
    parts = []
    for key, value in obs.items():
        if isinstance(value, dict) and "x" in value:
            parts.append(f"{key}({value['x']},{value['y']} d{value.get('dx', 0):+},{value.get('dy', 0):+})")
        elif not isinstance(value, (list, dict)):
            parts.append(f"{key}={value}")
    more = len(parts) - limit
    return " ".join(parts[:limit]) + (f" …{more} more" if more > 0 else "")


def _nodes_text(nodes: dict[str, Any]) -> str:
    return " ".join(f"{fn}={json.dumps(v)}" for fn, v in nodes.items()) or "-"


def _around_rows(episode: dict[str, Any]) -> list[tuple]:
    rows = []
    for entry in episode["around"]:
        for label in ("A", "B"):
            side = entry[label]
            mark = ">" if entry["step"] == episode["first_divergent_step"] else ""
            if side is None:
                rows.append((f"{mark}{entry['step']}", label, "(episode over)", "", ""))
                continue
            action = "-" if side["action"] is None else f"{side['action']} {side['action_name']}"
            rows.append((f"{mark}{entry['step']}", label, action, _nodes_text(side["nodes"]), _obs_text(side["obs"])))
    return rows


def _episode_headline(e: dict[str, Any]) -> list[str]:
    lines = [f"seed {e['seed']}: A return {e['A']['return']:g} in {e['A']['length']} steps ({e['A']['end_reason']}), "
             f"B return {e['B']['return']:g} in {e['B']['length']} steps ({e['B']['end_reason']})"]
    step = e["first_divergent_step"]
    if step is None:
        lines.append("  the two versions chose the same action at every step")
    else:
        lines.append(f"  first divergent step: {step} (A chose {_action(e, 'A')}, B chose {_action(e, 'B')})")
    return lines


def _action(e: dict[str, Any], label: str) -> str:
    at = next(x for x in e["around"] if x["step"] == e["first_divergent_step"])[label]
    if at is None:
        return "nothing: its episode had ended"
    return "no action (its policy failed)" if at["action"] is None else f"{at['action']} {at['action_name']}"


PAPER_NOTE = ("under the paper's protocol every seed is the same game, so the interval measures only the policies' "
              "own random draws, not how games vary; --audit plays each side on its own sealed audit seeds under the "
              "standard protocol")


def _seeds_text(seeds: list[int]) -> str:
    """A side's seeds: a run of consecutive ones as ``first..last`` (the paper's protocol), else each of them (the
    sealed audit's draws)."""
    if not seeds:
        return "no seeds"
    if len(seeds) == 1:
        return f"seed {seeds[0]}"
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"seeds {seeds[0]}..{seeds[-1]}"
    return "seeds " + ", ".join(str(s) for s in seeds)


def _score_lines(data: dict[str, Any]) -> list[str]:
    """Whether two versions' scores differ beyond the noise: each side's score (``store/scores.py``) with its
    seeds and returns, and the difference's verdict; a line on the protocol when it was the paper's."""
    if not data.get("scores"):
        return []
    lines = ["scores (store/scores.py: the mean return with its interval; no score for a side that forfeited a game):"]
    for label, side in data["scores"].items():
        seeds = side["seeds"]
        where = _seeds_text(seeds)
        ends = side.get("end_reasons") or [None] * len(side["returns"])
        returns = ", ".join(f"{r:g}" if end in (None, *PLAYED_OUT) else "forfeit"
                            for r, end in zip(side["returns"], ends))
        lines.append(f"  {label}: {side['summary']} ({where}; returns {returns})")
    lines += _difference_lines(data["difference"])
    if data.get("protocol") == "paper":
        lines.append(f"  ({PAPER_NOTE})")
    return lines


def _difference_lines(found: dict[str, Any]) -> list[str]:
    """The verdict (or why there is none: a side forfeited), and the sensitivity line when there is one."""
    lines = [f"  {found['verdict']}"]
    if (found.get("sensitivity") or {}).get("text"):
        lines.append(f"  {found['sensitivity']['text']}")
    return lines


def text_lines(data: dict[str, Any]) -> list[str]:
    """What ``codearcade compare`` prints on a terminal, terminal-safe (``viewers/safe_text.py``): a line each, but
    the tables and the diff, which span lines."""
    if data["mode"] == "runs":
        runs = data["runs"]
        lines = [format_table(("", "run", "model", "status", "iterations", "best", "held out", "at iteration",
                               "LLM calls", "tokens", "seconds"),
                              [(r["label"], r["run_id"], r["model"], r["status"], r["iterations"], _best(r),
                                _held_out(r), r["best_iteration"], r["llm_calls"], r["total_tokens"],
                                round(r["elapsed_s"], 1))
                               for r in runs], max_width=32, null="-", whole=("best", "held out")),
                 terminal_text(_best_difference(data)),
                 "", "best score reached within the same budget:",
                 format_table(("budget in", "up to", "A best", "B best"), _budget_rows(data), max_width=40, null="-"),
                 "", "diff of the best versions (A -> B):",
                 terminal_text(data["diff"] or "(the best versions are the same code)", multiline=True)]
        return lines
    versions = data["versions"]
    lines = [terminal_text(f"{v['label']} {v['ref']} ({v['policy_version_id']}), eval run {v['eval_run']}")
             for v in versions]
    for e in data["episodes"]:
        lines += [""] + [terminal_text(line) for line in _episode_headline(e)]
        if e["around"]:
            lines.append(format_table(("step", "", "action", "node outputs", "objects"), _around_rows(e),
                                      max_width=70, null="-"))
    lines += [""] + [terminal_text(line) for line in _score_lines(data)]
    lines += ["", "diff (A -> B):", terminal_text(data["diff"] or "(the same code)", multiline=True)]
    return lines


def write_report(data: dict[str, Any], out: Path) -> Path:
    """README.md (and ``curves.png`` for two runs) in ``out``; the README's path. Stored text is escaped for
    Markdown, and code is in fenced blocks no line of it can close (``viewers/safe_text.py``)."""
    out.mkdir(parents=True, exist_ok=True)
    md: list[str] = []
    if data["mode"] == "runs":
        with writing(out / "curves.png") as partial:
            save_png(curves_figure(data), partial)
        runs = data["runs"]
        md += [f"# {markdown_text(data['game'])}: run {markdown_code(runs[0]['run_id'])} (A) vs run "
               f"{markdown_code(runs[1]['run_id'])} (B)", "",
               "![learning curves against LLM calls, tokens and wall seconds](curves.png)", "",
               _md_table(("", "run", "model", "status", "iterations", "best", "held out", "at iteration",
                          "LLM calls", "tokens", "seconds"),
                         [(r["label"], markdown_code(r["run_id"]), r["model"], r["status"], r["iterations"], _best(r),
                           _held_out(r), r["best_iteration"], r["llm_calls"], r["total_tokens"], r["elapsed_s"])
                          for r in runs]),
               "", markdown_text(_best_difference(data)) + " (`store/scores.py`)",
               *(f"\n**Caution:** {markdown_text(c)}." for c in data.get("cautions", ())),
               "", "## Best score within the same budget", "",
               "Only budgets both runs spent are matched; `all` is each run's whole spending.", "",
               _md_table(("budget in", "up to", "A best", "B best"), _budget_rows(data)), "",
               "## Diff of the best versions", "", markdown_code_block(data["diff"] or "(the same code)", "diff"), ""]
    else:
        versions = data["versions"]
        md += [f"# {markdown_text(data['game'])}: {markdown_text(versions[0]['ref'])} (A) vs "
               f"{markdown_text(versions[1]['ref'])} (B)", ""]
        md += [f"- {markdown_text(v['label'])}: {markdown_text(v['ref'])}, version "
               f"{markdown_code(v['policy_version_id'])}, eval run {markdown_code(v['eval_run'])}" for v in versions]
        for e in data["episodes"]:
            md += ["", f"## Seed {e['seed']}", ""] + [markdown_text(line.strip()) for line in _episode_headline(e)]
            if e["around"]:
                md += ["", _md_table(("step", "", "action", "node outputs", "objects"), _around_rows(e))]
        scores = _score_lines(data)
        if scores:
            md += ["", "## Scores", "", markdown_text(scores[0]), ""]
            md += [f"- {markdown_text(line.strip())}" for line in scores[1:]]
        md += ["", "## Diff", "", markdown_code_block(data["diff"] or "(the same code)", "diff"), ""]
    readme = out / "README.md"
    with writing(readme) as partial:
        partial.write_text("\n".join(md))
    return readme
