"""One Rerun recording per optimization run, rebuilt from the store: the learning curve beside the code.

Recording: application id ``codearcade``, recording id = the run id. Timeline ``iteration`` (sequence).

Entity layout::

    /score/score                 Scalars: mean evaluation return of the version evaluated in the iteration
    /score/best                  Scalars: best score so far
    /score/train_return          Scalars: return of the traced training rollout
    /llm/tokens/input            Scalars: input tokens of the iteration's LLM call (as the provider reported)
    /llm/tokens/output           Scalars: output tokens
    /llm/tokens/prompt_counted   Scalars: our own count of the prompt (held against --token-budget)
    /llm/cost_usd                Scalars: cost, where litellm knows the model's price
    /llm/latency_s               Scalars: seconds of the call
    /llm/prompt                  TextDocument: the messages sent, per iteration
    /llm/reply                   TextDocument: the reply text (or the call's error), per iteration
    /metrics/loc                 Scalars: lines of the evaluated policy file (radon)
    /metrics/complexity          Scalars: cyclomatic complexity of its Policy class
    /metrics/max_if_depth        Scalars: deepest nesting of ``if``
    /code                        TextDocument (markdown): the whole policy file evaluated in the iteration
    /feedback                    TextDocument: the feedback the next prompt shows
    /log                         TextLog: one line per iteration (update status, score, best, rollback)
    /lineage                     GraphNodes + GraphEdges: every candidate so far (x: iteration, y: score, colour:
                                 the strategy's decision) with an edge from the candidate it improved
    properties                   ``run``: run_id, kind, game, model, seed, status, iterations, created_at

Blueprint: score, code metrics and token series on the left; the code (with prompt, reply, feedback and the
lineage graph in tabs beside it) on the right, so scrubbing the ``iteration`` timeline shows the code that scored each point.
"""

from __future__ import annotations

import json
from typing import Any

import duckdb
import rerun as rr
import rerun.blueprint as rrb

from store import Store
from store.scores import score_text
from store.showing import run_timeline
from viewers.rerun_recording import new_recording, resolve_recording
from viewers.safe_text import markdown_code_block, plain_text


def read_run(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any]:
    """The run row, its iterations (joined with the evaluated version, the LLM call, the feedback) and texts."""
    return run_timeline(con, run_id)


def prompt_text(stored: str | None) -> str:
    """The stored prompt (canonical JSON of the messages) as readable text, one section per message."""
    if stored is None:
        return ""
    try:
        messages = json.loads(stored)
        return "\n\n".join(f"===== {m.get('role', '?')} =====\n{m.get('content', '')}" for m in messages)
    except (ValueError, AttributeError, TypeError):
        return stored


def log_run(data: dict[str, Any], recording: rr.RecordingStream | None = None) -> None:
    """Log a run read by :func:`read_run` into ``recording`` (or the ambient one)."""
    rec = resolve_recording(recording)
    run = data["run"]
    iterations = data["iterations"]
    props = {k: run[k] for k in ("run_id", "kind", "game", "model", "seed", "status", "error") if run[k] is not None}
    props["created_at"] = str(run["created_at"])
    props["iterations"] = len(iterations)
    picked = data.get("best") or {}
    if picked.get("policy_version_id") is not None:  # the run's best, as every verb names it (view run_best)
        props.update(best_version_id=picked["policy_version_id"], best_iteration=picked["iteration"],
                     best_by=picked["best_by"])
    rec.send_property("run", rr.AnyValues(**props))
    for name in ("score", "train_return"):
        rec.log(f"/score/{name}", rr.SeriesLines(names=name), static=True)
    rec.log("/score/best", rr.SeriesLines(names="best", interpolation_mode="StepAfter"), static=True)
    for name in ("loc", "complexity", "max_if_depth"):
        rec.log(f"/metrics/{name}", rr.SeriesPoints(names=name), static=True)

    for it in iterations:
        rec.set_time("iteration", sequence=int(it["iteration"]))
        for name, value in (("score", it["score"]), ("best", it["best_score"]), ("train_return", it["train_return"])):
            if value is not None:
                rec.log(f"/score/{name}", rr.Scalars(float(value)))
        for name in ("loc", "complexity", "max_if_depth"):
            if it[name] is not None:
                rec.log(f"/metrics/{name}", rr.Scalars(float(it[name])))
        for path, key in (("tokens/input", "input_tokens"), ("tokens/output", "output_tokens"),
                          ("tokens/prompt_counted", "prompt_tokens_counted"), ("cost_usd", "cost_usd"),
                          ("latency_s", "latency_s")):
            if it[key] is not None:
                rec.log(f"/llm/{path}", rr.Scalars(float(it[key])))
        if it["code"] is not None:
            rec.log("/code", rr.TextDocument(markdown_code_block(it["code"], "python"), media_type="text/markdown"))
        if it["prompt"] is not None:
            rec.log("/llm/prompt", rr.TextDocument(plain_text(prompt_text(it["prompt"])), media_type="text/plain"))
        reply = _whole_or_cut(it["reply"], it["reply_length"], "reply")
        if reply is None and it["error_type"]:
            reply = f"(the call failed: {it['error_type']}: {it['error_message']})"
        if reply is not None:
            if it["parse_error"]:
                reply = f"(not usable: {it['parse_error']})\n\n{reply}"
            rec.log("/llm/reply", rr.TextDocument(plain_text(reply), media_type="text/plain"))
        if it["feedback"] is not None:
            rec.log("/feedback", rr.TextDocument(
                plain_text(_whole_or_cut(it["feedback"], it["feedback_length"], "feedback")), media_type="text/plain"))
        score = "-" if it["score"] is None else score_text(it["score"])
        if it["score"] is None and it.get("forfeit"):  # a forfeit is never scored: say so, and why
            score = f"none ({it['forfeit']})"
        best = "-" if it["best_score"] is None else score_text(it["best_score"])
        # a served run's best so far is by training score: its finalize picks the run's best by validation
        best = f"best training score {best}" if run["kind"] == "serve" else f"best {best}"
        line = (f"iteration {it['iteration']}: update {it['update_status']}, score {score}, {best} "
                f"(iteration {it['best_iteration']}), version {it['policy_version_id']}"
                + (", rolled back" if it["rolled_back"] else ""))
        level = rr.TextLogLevel.WARN if it["update_status"] in ("rejected", "llm_error") else rr.TextLogLevel.INFO
        rec.log("/log", rr.TextLog(line, level=level))
        _log_lineage(rec, data.get("lineage") or [], int(it["iteration"]))
    if picked.get("best_by") == "validation":  # the run's best (view run_best), after its last submission
        chosen = ("no best: every submission forfeited a validation game" if picked["policy_version_id"] is None
                  else f"best by validation {score_text(picked['score'])} (iteration {picked['iteration']}), version "
                  f"{picked['policy_version_id']}")
        rec.log("/log", rr.TextLog(f"finalized: {chosen}", level=rr.TextLogLevel.INFO))
    rec.reset_time()
    rec.send_blueprint(run_blueprint())


LINEAGE_COLOURS = {"best": (255, 127, 14), "kept": (31, 119, 180), "discarded": (170, 170, 170),
                   "rolled_back": (148, 103, 189), "rejected": (214, 39, 40)}


def _whole_or_cut(text: str | None, length: int | None, what: str) -> str | None:
    """A stored text as a recording shows it: whole, or its start (``store/showing.py`` reads no more) and how much
    was left out."""
    if text is None or length is None or length <= len(text):
        return text
    return (f"{text}\n\n[... the {what} goes on for {length - len(text):,} more characters: "
            f"{length:,} in all; `codearcade sql` reads the whole]")


def _log_lineage(rec: rr.RecordingStream, lineage: list[dict[str, Any]], iteration: int) -> None:
    """The candidates up to ``iteration`` as a directed graph (parent -> candidate): x is the iteration, y the
    score (higher is better), colour the strategy's decision."""
    nodes = [n for n in lineage if n["iteration"] <= iteration]
    if not nodes:
        return
    scores = [n["score"] for n in lineage if n["score"] is not None] or [0.0]
    low, span = min(scores), (max(scores) - min(scores)) or 1.0
    ids = {(n["iteration"], n["candidate"]): f"{n['iteration']}.{n['candidate']}" for n in nodes}
    rec.log("/lineage", rr.GraphNodes(
        node_ids=[ids[(n["iteration"], n["candidate"])] for n in nodes],
        positions=[(n["iteration"] * 120.0, -400.0 * ((n["score"] if n["score"] is not None else low) - low) / span)
                   for n in nodes],
        labels=[f"{n['iteration']}.{n['candidate']}: {'-' if n['score'] is None else format(n['score'], 'g')}"
                for n in nodes],
        colors=[LINEAGE_COLOURS.get(n["decision"], (120, 120, 120)) for n in nodes]),
        rr.GraphEdges(edges=[(ids[(n["parent_iteration"], n["parent_candidate"] or 0)],
                              ids[(n["iteration"], n["candidate"])]) for n in nodes
                             if (n["parent_iteration"], n["parent_candidate"] or 0) in ids],
                      graph_type="directed"))


def run_blueprint() -> rrb.Blueprint:
    """Score, metrics and tokens on the left; the code beside them (prompt, reply, feedback in tabs)."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/score", name="score"),
                rrb.TimeSeriesView(origin="/metrics", name="code metrics (loc, complexity, if depth)"),
                rrb.TimeSeriesView(origin="/llm/tokens", name="tokens"),
                rrb.TextLogView(origin="/log", name="iterations"),
                row_shares=[3, 2, 2, 2],
            ),
            rrb.Tabs(
                rrb.TextDocumentView(origin="/code", name="policy code"),
                rrb.TextDocumentView(origin="/llm/prompt", name="prompt"),
                rrb.TextDocumentView(origin="/llm/reply", name="reply"),
                rrb.TextDocumentView(origin="/feedback", name="feedback"),
                rrb.GraphView(origin="/lineage", name="lineage"),
                active_tab=0,
            ),
            column_shares=[1, 1],
        ),
        collapse_panels=True,
    )


def run_recording(store: Store, run_id: str, recording: rr.RecordingStream | None = None) -> rr.RecordingStream:
    """Rebuild a run's recording from ``store`` into ``recording`` (default: a new stream, id = the run id)."""
    with store.read() as con:
        data = read_run(con, run_id)
    rec = recording if recording is not None else new_recording(run_id, f"{run_id} ({data['run']['game']})")
    log_run(data, rec)
    return rec
