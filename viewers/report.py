"""``codearcade report RUN``: PNG plots and a Markdown summary of one run, from the store alone.

An optimization run gets ``score.png`` (mean evaluation return per iteration, each evaluation episode, the
best so far, rollbacks), ``code.png`` (lines of code, cyclomatic complexity and nested-if depth of the version
each iteration evaluated: the paper's Table 3 over time) and ``tokens.png`` (LLM input/output tokens per
iteration and cumulative) and ``lineage.png`` (every candidate at its score, with an edge to the candidate it
improved, and its standard-protocol score when measured; a candidate never played, hollow on a lane of its own); an eval run gets ``score.png`` with the return of each episode. ``README.md`` shows
the plots with the run's settings and tables of its iterations (or episodes), rejected candidates and LLM
usage; every text read from the store is escaped for Markdown (``viewers/safe_text.py``: an episode's error
cannot add HTML, a link or an image to the page), and the command lines are a fenced block no text can close.
Everything is read in one read-only open (the views of docs/schema.md), so a report can be made while the run is
still writing; the plots are ``viewers/report_figures.py``'s, drawn with matplotlib's Agg canvas (no display).
"""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Sequence

from store import Store
from store.readers import get_run, model_choice_rows
from store.scores import NO_REFERENCE, score_episodes
from store.statistics import MEAN_METHOD, interval_text
from store.showing import report_rows
from store.runs import resolve_run_id, shown_status
from viewers.model_choices import choice_section
from viewers.report_figures import (calls_figure, code_figure, lineage_figure, save_png, scores_figure,
                                    tokens_figure)
from viewers.safe_text import (markdown_cell, markdown_code, markdown_code_block, markdown_text, terminal_text)
from viewers.tables import money
from viewers.whole_files import writing

def collect(store: Store, run: str) -> dict[str, Any]:
    """Everything a report shows, read in one open of the store."""
    with store.read() as con:
        run_id = resolve_run_id(con, run, store)
        data: dict[str, Any] = {"run": get_run(con, run_id)}
        data["run"]["status"] = shown_status(store.path, run_id, data["run"].get("status"))

        data.update(report_rows(con, run_id))
        data["choices"] = model_choice_rows(con, run_id)  # an ensemble's reasons (viewers/model_choices.py)
    # a store is anyone's file: settings or package versions that are no JSON object are shown as none, and the
    # command that reproduces the run gets the settings as stored, to say they cannot be read
    try:
        data["recorded"] = json.loads(data["run"]["config"]) if data["run"]["config"] else {}
    except RecursionError:  # nested deeper than the decoder follows (a list 10,000 deep): no settings either
        data["recorded"] = data["run"]["config"]
    data["config"] = data["recorded"] if isinstance(data["recorded"], dict) else {}
    packages = json.loads(data["run"]["package_versions"] or "{}")
    data["packages"] = packages if isinstance(packages, dict) else {}
    return data


# --------------------------------------------------------------------------------------------------- plots

def _md(value: Any, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}".rstrip("0").rstrip(".") if abs(value) < 1e6 else f"{value:.3g}"
    if isinstance(value, datetime):
        return value.strftime("%Y-%m-%d %H:%M:%S UTC")
    if isinstance(value, (dict, list)):
        value = json.dumps(value)
    return markdown_cell(value)  # stored text is escaped (an episode's error may hold <script> or a link)


def _score_text(row: dict[str, Any]) -> str:
    """A scored row's score with its interval, level, method and n (``store.statistics.interval_text``; the row's
    ``score_low``/``score_high``/``score_n`` are :func:`store.showing.report_rows`'s, computed by today's rule)."""
    return interval_text(row["score"], row.get("score_low"), row.get("score_high"), row.get("score_n") or 0,
                         MEAN_METHOD)


def _stale_audit(summary: dict[str, Any], run: dict[str, Any]) -> str:
    """Why the audit below is not the best's (``run_summary.audit_stale``): the run went on after it."""
    return (f"not of the run's best: it played the best of iteration {summary['audit_iteration']}, and the run went "
            f"on to a new one ({markdown_code('codearcade audit ' + run['run_id'])} audits it)")


def _audit_text(row: dict[str, Any] | None) -> str:
    """A side of the held-out audit in the headline: its score with its interval, or why it has none."""
    if row is None:
        return "not audited"
    return _score_text(row) if row["score"] is not None else "forfeit"


def _md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(_md(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _settings(data: dict[str, Any]) -> list[tuple[str, Any]]:
    run, summary, config = data["run"], data["summary"], data["config"]
    rows: list[tuple[str, Any]] = [("run id", markdown_code(run["run_id"]))] + ([("name", run["name"])] if run.get("name") else [])
    rows += [("kind", run["kind"]), ("game", run["game"]), ("model", run["model"]), ("status", run["status"]),
             ("seed", run["seed"]), ("created", run["created_at"]), ("finished", run["finished_at"]),
             ("duration (s)", summary["duration_s"])]
    if run["error"]:
        rows.append(("error", run["error"]))
    skip = {"game", "model", "seed", "instruction", "feedback_bands"}
    rows += [(markdown_code(k), v) for k, v in sorted(config.items()) if k not in skip]
    bands = config.get("feedback_bands")
    if isinstance(bands, dict):
        rows.append(("feedback bands", f"high ≥ {bands.get('high')}, low ≤ {bands.get('low')}, "
                                       f"target {bands.get('target')}"))
    return rows


def _functions_table(version: dict[str, Any]) -> str:
    functions = version.get("functions") or []
    return _md_table(("method", "trainable", "SLOC", "complexity", "if depth"),
                     [(f["name"], f["trainable"], f["sloc"], f["complexity"], f["max_if_depth"]) for f in functions])


def render_markdown(data: dict[str, Any], images: dict[str, str], reproduce: Callable[..., str] | None = None,
                    price: Callable[[str], Any] | None = None) -> str:
    """The report's README.md (``images``: file name -> caption, of the plots written). ``reproduce(run, config)``
    is the command line that starts a run with the same settings, ``price(model)`` the model's rates per token
    (see :func:`write_report`)."""
    run, summary, usage = data["run"], data["summary"], data["usage"]
    named = f" ({markdown_text(run['name'])})" if run.get("name") else ""
    out = [f"# {markdown_text(run['game'])} {markdown_text(run['kind'])} run {markdown_code(run['run_id'])}{named}", ""]
    facts = [f"status **{markdown_text(run['status'])}**"]
    forfeits = summary.get("forfeits") or 0
    if run["kind"] == "eval":
        score = score_episodes(e for e in data["episodes"] if e["kind"] == "eval")
        if score.forfeits:  # the one rule (store/scores.py): no score, and the played-out mean is not one
            facts.append(f"**{markdown_text(score.no_score)}**"
                         + (f" ({markdown_text(score.played_out_text())})" if score.played_out_text() else ""))
        else:
            facts.append(f"score **{markdown_text(score.summary())}**")
    else:
        facts.append(f"{summary['iterations_done']} submissions" if run["kind"] == "serve"  # by a coding agent
                     else f"{summary['iterations_done']} of {_md(summary['iterations_planned'])} iterations")
        if summary.get("best_by") == "validation":  # a finalized served run: its best is the validation pick
            facts.append("**no best**: every submission forfeited a validation game" if summary["best_version_id"]
                         is None else f"best by validation **{_md(summary['best_score'])}** (iteration "
                         f"{_md(summary['best_iteration'])}; training {_md(summary['best_training_score'])})")
        elif summary["best_score"] is None and forfeits:  # a played-out score beats a forfeit: none played out
            facts.append("**no score**: every version it assessed forfeited a game")
        else:
            training = " by training score (not finalized)" if summary.get("best_by") == "training" else ""
            facts.append(f"best score{training} **{_md(summary['best_score'])}** (iteration "
                         f"{_md(summary['best_iteration'])})")
        if forfeits:
            facts.append(f"{forfeits} candidate(s) forfeited a game"
                         + (" (never the best)" if summary["best_score"] is not None else ""))
        audited = {a["role"]: a for a in data.get("audits") or () if a["protocol"] == "standard"}
        if summary.get("audit_stale"):  # it went on after its audit: that score is an earlier best's, not this one's
            facts.append(f"held-out audit: {_stale_audit(summary, run)}")
        elif "best" in audited:  # each side's score, or "forfeit": a starter that forfeited its audit showed as "–"
            best, starter = (_audit_text(audited.get(role)) for role in ("best", "starter"))
            facts.append(f"held-out audit **{best}** (standard protocol; starter {starter})"
                         + (" · **OVERFIT**: less than half of the gain over the starter holds up"
                            if summary["overfit"] else f" · overfit: {NO_REFERENCE}" if summary["overfit"] is None
                            else ""))
        facts.append(f"{summary['total_tokens']:,} LLM tokens")
        if summary.get("repair_calls"):
            saved = summary.get("saved_by_repair") or 0
            facts.append(f"{summary['repair_calls']} repair call{'s' * (summary['repair_calls'] > 1)}, {saved} "
                         f"update{'s' * (saved != 1)} saved by a repair")
    facts.append(f"created {_md(run['created_at'])}")
    out += [" · ".join(facts), ""]
    for name, caption in images.items():
        out += [f"![{caption}]({name})", ""]

    if run["kind"] == "eval":
        out += ["## Episodes", "", _md_table(
            ("episode", "seed", "return", "length", "lives lost", "end reason", "seconds", "error"),
            [(e["episode_index"], e["seed"], e["return"], e["length"], e["lives_lost"], e["end_reason"],
              e["duration_s"], terminal_text(e["error"] or "")[:120])
             for e in data["episodes"] if e["kind"] == "eval"]),
                ""]
    else:
        code = {r["iteration"]: r for r in data["code"]}
        rows = []
        for r in data["curve"]:
            c = code.get(r["iteration"], {})
            status = r["update_status"] + (" ↺ rolled back" if r["rolled_back"] else "")
            if r.get("repairs"):
                status += f" after {r['repairs']} repair{'s' * (r['repairs'] > 1)}"
            score = (r["score"] if not r.get("forfeit") else f"no score: {terminal_text(r['forfeit'])}")
            if r["score"] is not None and r.get("score_n", 0) >= 2:  # one episode: the number alone
                score = _score_text(r)
            rows.append((r["iteration"], status, score, r["best_score"], r["train_return"], c.get("loc"),
                         c.get("sloc"), c.get("complexity"), c.get("max_if_depth"), r["input_tokens"],
                         r["output_tokens"], r["wall_s"], markdown_code(r["policy_version_id"])))
        out += ["## Iterations", "",
                "Score: mean evaluation return, with its 95% Student-t interval over its n episodes (from two "
                "episodes; none when they all returned the same, which under the paper's protocol is one game "
                "played n times); "
                "an iteration whose version ended a game itself (an error, a time limit) has no score: a forfeit "
                "(never the best). Train: return of the traced training rollout. Code metrics are "
                "those of the version evaluated (`code_metrics`); tokens are those of the iteration's LLM calls.", "",
                _md_table(("iteration", "update", "score", "best", "train", "LOC", "SLOC", "complexity", "if depth",
                           "tokens in", "tokens out", "wall s", "version"), rows), ""]
        if data.get("audits"):
            out += ["## Validation and held-out pools", "",
                    "The run's finalize (`codearcade serve`): each submission on the sealed validation pool, the "
                    "best by validation and the starting policy on the sealed held-out pool (seeds from 1,000,000, "
                    "the standard protocol: sticky actions 0.25, up to 30 no-op starts); tuning: the training "
                    "score. Overfit: less than half of the best's gain over the starter holds up.", ""] \
                if run["kind"] == "serve" else ["## Held-out audit", "",
                    "The best version and the starting policy on seeds the loop never played (from 1,000,000), "
                    "under the standard protocol (sticky actions 0.25, up to 30 no-op starts) and the run's own; "
                    "tuning: its score on the seeds the loop selected on. Overfit: less than half of the best's "
                    "gain over the starter holds up (`codearcade audit` plays it again).", ""]
            if summary.get("audit_stale"):
                out += [f"**{_stale_audit(summary, run)}**.", ""]
            out += [
                    _md_table(("version", "iteration", "protocol", "games", "score (95% interval, method, n)",
                               "tuning", "overfit"),
                              [(a["role"], a["iteration"], a["protocol"], len(a["seeds"]),
                                _score_text(a) if a["score"] is not None
                                else f"forfeit: {terminal_text(a['forfeit'])}", a["tuning_score"],
                                "no reference" if a["overfit"] is None and (a["role"], a["protocol"]) == (
                                    "best", "standard") else a["overfit"])
                               for a in data["audits"]]), ""]
        if data["rejected"]:
            out += ["## Rejected candidates", "", _md_table(
                ("iteration", "stage", "reason"),
                [(r["iteration"], r["stage"], terminal_text(r["reason"] or "")[:300]) for r in data["rejected"]]), ""]
        if usage["calls"]:
            out += ["## LLM usage", "", _md_table(
                ("calls", "errors", "unusable replies", "retries", "input tokens", "cached input tokens",
                 "output tokens", "cost (USD)", "mean latency (s)", "max latency (s)", "models"),
                [(usage["calls"], usage["errors"], usage["parse_errors"], usage["retries"], usage["input_tokens"],
                  usage.get("cached_input_tokens"), usage["output_tokens"], money(usage["cost_usd"]),
                  usage["mean_latency_s"], usage["max_latency_s"], usage["request_models"])]), ""]
            saving = _cache_saving(run, usage, price)
            if saving:
                out += [saving, ""]
        if len(data.get("models") or ()) > 1:  # an ensemble: what each model's calls brought (view model_stats)
            out += ["## Models", "", _md_table(
                ("model", "calls", "share", "accepted", "improvements", "gain", "cost (USD)",
                 "cost per improvement (USD)", "mean latency (s)"),
                [(terminal_text(m["model"] or ""), m["calls"], f"{m['share']:.0%}", m["accepted"], m["improvements"],
                  m["gain"], money(m["cost_usd"]), money(m["cost_per_improvement"]), m["mean_latency_s"])
                 for m in data["models"]]), ""]
            out += choice_section(data.get("choices") or [])
    best_id = summary.get("best_version_id") if run["kind"] != "eval" else None  # view run_best's
    version = next((v for v in data["versions"] if v["policy_version_id"] == (best_id or run["starter_version_id"])
                    and v["validation"] != "rejected"), None)
    if version is not None:
        which = "best version" if best_id else "policy"
        out += [f"## Methods of the {which} ({markdown_code(version['policy_version_id'])})", "",
                f"{version['loc']} lines, {version['sloc']} source lines, cyclomatic complexity "
                f"{version['complexity']}, nested-if depth {version['max_if_depth']}.", "",
                _functions_table(version), ""]
    out += ["## Settings", "", _md_table(("setting", "value"), _settings(data)), ""]
    if data["config"].get("instruction"):
        out += ["Instruction given to the model:", "",
                "\n".join("> " + markdown_text(line) for line in str(data["config"]["instruction"]).splitlines()), ""]
    if data["packages"]:
        out += ["Package versions: " + ", ".join(markdown_text(f"{k} {v}") for k, v in sorted(data["packages"].items())),
                ""]
    query = ("SELECT episode_index, seed, return, length, end_reason FROM episodes WHERE run_id = '{}' "
             "ORDER BY episode_index" if run["kind"] == "eval" else
             "SELECT * FROM learning_curve WHERE run_id = '{}' ORDER BY iteration").format(run["run_id"])
    same = ("a served run draws its training games anew, so only its settings repeat" if run["kind"] == "serve"
            else "with a deterministic policy and model it plays the same episodes")
    out += ["## Reproduce", "", f"The command that made this run (a new run with the same settings; {same}), and "
            "the queries behind this report:", "",
            markdown_code_block("\n".join([*([reproduce(run, data.get("recorded", data["config"]))]
                                              if reproduce is not None else []),
                                            f"codearcade report {run['run_id']}", f'codearcade sql "{query}"']),
                                "bash"), ""]
    return "\n".join(out)


def _cache_saving(run: dict[str, Any], usage: dict[str, Any], price: Callable[[str], Any] | None) -> str | None:
    """A sentence on what prompt caching saved, at the model's prices (``price(model)``: rates per token with
    ``input`` and ``cached_input``, or None), or None."""
    cached = usage.get("cached_input_tokens") or 0
    if not cached or not run.get("model"):
        return None
    rates = price(run["model"]) if price is not None else None
    share = cached / max(usage["input_tokens"] or 1, 1)
    if rates is None or rates.cached_input is None:
        return f"Prompt caching: {cached:,} input tokens ({share:.0%}) were read from the provider's cache."
    saved = cached * (rates.input - rates.cached_input)
    return (f"Prompt caching: {cached:,} input tokens ({share:.0%}) were read from the provider's cache, "
            f"saving about ${saved:.4f} at {markdown_text(run['model'])}'s prices.")


def write_report(store: Store, run: str, out_dir: str | Path | None = None, *,
                 reproduce: Callable[[dict[str, Any], dict[str, Any]], str] | None = None,
                 price: Callable[[str], Any] | None = None, progress: Callable[[str], None] | None = None) -> Path:
    """Write the plots and README.md of ``run`` (an id or unique prefix) into ``out_dir``; return README's path.

    What the report cannot know without the pipeline comes in from its caller (viewers never import it):
    ``reproduce(run row, config)``, the command line that starts a run with the same settings, and
    ``price(model)``, the model's rates per token (``input``, ``cached_input``) or None, for what prompt caching
    saved. Without them, the Reproduce section shows only the queries and the caching line only the tokens.
    ``progress`` gets a line as each stage starts (reading the run, each figure, the Markdown): a long report is
    never a silent wait."""
    say = progress or (lambda line: None)
    say("reading the run from the store")
    data = collect(store, run)
    out = Path(out_dir) if out_dir else Path("reports") / data["run"]["run_id"]
    out.mkdir(parents=True, exist_ok=True)
    images: dict[str, str] = {}
    for name, figure, caption in (
        ("score.png", scores_figure, "Return per episode" if data["run"]["kind"] == "eval" else "Score per iteration"),
        ("code.png", code_figure, "Code size and complexity per iteration"),
        ("tokens.png", tokens_figure, "LLM tokens per iteration"),
        ("lineage.png", lineage_figure, "Every candidate and the version it improved"),
        ("calls.png", calls_figure, "LLM calls over time: model, calls in flight, what came of each"),
    ):
        if data["run"]["kind"] == "eval" and name != "score.png":
            continue
        say(f"drawing {name}")
        fig = figure(data)
        if fig is not None:
            with writing(out / name) as partial:
                save_png(fig, partial)
            images[name] = caption
    readme = out / "README.md"
    say("writing README.md")
    with writing(readme) as partial:
        partial.write_text(render_markdown(data, images, reproduce, price))
    return readme
