"""A scripted coding agent for ``codearcade serve``: an MCP client that improves the Pong starter from the feedback it
reads, within the run's episode budget.

It starts ``codearcade serve --mcp`` itself (as Claude Code or Codex CLI would, over stdio), reads the task,
plays the starting policy, and then edits the policy from what each submission's feedback shows:

- the trace's calls show ``select_action`` ignoring ``predicted_ball_y`` (its actions do not follow the
  prediction) while points are lost: it rewrites ``select_action`` to steer the paddle to the prediction;
- points are still lost and the prediction is the ball's current ``y`` (no look-ahead): it rewrites
  ``predict_ball_trajectory`` to extrapolate the ball to the paddle's plane, bouncing off the walls;
- then, while the budget lasts, it moves the paddle's dead band (``MARGIN``) up or down and keeps whichever
  scored better on the same training instances (a hill climb on the feedback's scores), until every neighbour of
  the best has been tried.

Every rewrite is submitted with ``parent`` = the best submission so far, so the run's lineage shows the climb.
When the budget is spent the server finalizes the run (sealed validation and held-out pools) by itself; an agent
that stops earlier calls ``finalize``.

    python examples/serve_agent.py --store /tmp/agent.duckdb -- --budget 24 --max-steps 1000

Everything after ``--`` goes to ``codearcade serve`` (its flags: ``codearcade serve --help``). It prints one line
per submission and, last, the run id.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

TRACKING_SELECT = '''def select_action(self, predicted_ball_y, obs):
    """Steer the paddle's centre (where it will be next step) to the predicted y; hold within MARGIN."""
    MARGIN = {margin}
    player = obs.get("Player")
    if player is None or predicted_ball_y is None:
        return 0
    paddle = player["y"] + player["h"] / 2 + player["dy"]
    if paddle < predicted_ball_y - MARGIN:
        return 3
    if paddle > predicted_ball_y + MARGIN:
        return 2
    return 0
'''

BOUNCING_PREDICT = '''def predict_ball_trajectory(self, obs):
    """Where the ball's centre reaches x=140, bouncing off y=30 and y=190; its y when it moves away."""
    ball = obs.get("Ball")
    if ball is None:
        return None
    centre = ball["y"] + ball["h"] / 2
    if ball["dx"] <= 0:
        return centre
    y = centre + ball["dy"] * (140 - ball["x"]) / ball["dx"]
    offset = (y - 30) % 320
    return 30 + (offset if offset <= 160 else 320 - offset)
'''


def _ignores_prediction(trace: dict[str, Any]) -> bool:
    """Whether the traced steps show actions that do not follow the prediction: the paddle is told to go up while
    the prediction is below it, or down while above (judged from the calls lines the feedback shows)."""
    against = 0
    for step in trace["steps"]:
        calls = step["calls"]
        if "predicted_ball_y=" not in calls or "-> " not in calls:
            continue
        try:
            predicted = float(calls.split("predicted_ball_y=")[1].split(",")[0])
            paddle_y = float(step["observation"].split("Player(")[1].split(",")[1])
            action = int(calls.rsplit("-> ", 1)[1].split()[0])
        except (IndexError, ValueError):
            continue
        if (action == 2 and predicted > paddle_y + 15) or (action == 3 and predicted < paddle_y):
            against += 1
    return against >= 3


def _points_lost(trace: dict[str, Any]) -> int:
    return sum(1 for event in trace["events"] if event.startswith("point lost"))


def _replace(text: str, sources: dict[str, str]) -> str:
    sys.path.insert(0, str(ROOT))
    from tracing.policy_file import replace_methods

    return replace_methods(text, sources)


async def agent(serve_args: list[str], log=print) -> str:
    from mcp import Client
    from mcp.client.stdio import StdioServerParameters

    params = StdioServerParameters(command=sys.executable, args=["-m", "pipeline.cli", "serve", "--mcp", "--game",
                                                                 "pong", *serve_args],
                                   cwd=str(ROOT))
    async with Client(params, read_timeout_seconds=1800) as client:
        async def call(tool: str, **arguments: Any) -> dict[str, Any]:
            result = await client.call_tool(tool, arguments)
            if result.is_error:
                raise RuntimeError(f"{tool}: {result.content[0].text}")
            return result.structured_content

        task = await call("task")
        per = min(task["per_submission"], 4, task["budget"]["remaining"])
        instances = list(range(min(per, task["instances"])))
        best = {"text": task["starter_policy"], "submission": 0, "score": None}
        margin = 4

        async def submit(text: str, why: str) -> dict[str, Any] | None:
            if (await call("budget"))["remaining"] < len(instances):
                return None
            answer = await call("submit", policy=text, instances=instances, parent=best["submission"])
            score = answer["score"]
            log(f"submission {answer['submission']}: {why}: score "
                f"{'forfeit' if score is None else format(score, 'g')}")
            if score is not None and (best["score"] is None or score > best["score"]):
                best.update(text=text, submission=answer["submission"], score=score)
            return answer

        await submit(task["starter_policy"], "the starting policy")
        feedback = await call("feedback", submission=best["submission"], steps=60)
        text = best["text"]
        if _points_lost(feedback["trace"]) and _ignores_prediction(feedback["trace"]):
            text = _replace(text, {"select_action": TRACKING_SELECT.format(margin=margin)})
            await submit(text, "select_action steers to the prediction (the trace showed it ignored it)")
            feedback = await call("feedback", submission=best["submission"], steps=60)
        if _points_lost(feedback["trace"]) and "def predict_ball_trajectory" in best["text"] and \
                "% 320" not in best["text"]:
            await submit(_replace(best["text"], {"predict_ball_trajectory": BOUNCING_PREDICT}),
                         "predict_ball_trajectory extrapolates with bounces (points still lost)")
        tried = {margin}
        while "MARGIN = " in best["text"]:  # hill climb on the dead band while the budget lasts
            candidate = next((margin + d for d in (2, -2, 1, -1) if margin + d >= 0 and margin + d not in tried), None)
            if candidate is None:  # every neighbour of the best tried: nothing left worth the budget
                break
            tried.add(candidate)
            text = best["text"].replace(f"MARGIN = {margin}", f"MARGIN = {candidate}")
            before = best["submission"]
            if await submit(text, f"MARGIN {margin} -> {candidate}") is None:
                break
            if best["submission"] != before:
                margin = candidate
        if not (await call("budget"))["finalized"]:
            await call("finalize")  # the budget is not spent: end the run here (sealed validation and held-out)
        return task["run"]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    own, serve_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", help="the store of the served run (codearcade serve --store)")
    args = parser.parse_args(own)
    run_id = asyncio.run(agent((["--store", args.store] if args.store else []) + serve_args))
    print(f"run {run_id}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
