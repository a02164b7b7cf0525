"""The CPU of reading a streamed reply: codearcade's client against litellm's default reading of the same stream.

litellm hands every event of a stream to its logging callbacks, each on a thread of its own in an event loop made
for it; codearcade registers no litellm callback (the store is its log) and turns that off
(``pipeline/llm/tokens.py``). This bench streams a reply of ``--pieces`` word-sized pieces (a 2,000-token policy
is about 1,600) from the scripted server (tests/scripted_llm.py) through litellm's real OpenAI and Anthropic
adapters with ``LiteLLMClient``, alternately with litellm's streaming logging on (its default) and off (as
codearcade reads), and prints this process's CPU per call, the logging threads' included (each call is measured
until litellm's logging queue is empty), and their ratio. The server is a process of its own: its CPU is not
counted. Target: codearcade / litellm's default <= 0.6.

    .venv/bin/python bench/stream_read.py [--pieces 1600] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")

from pipeline.llm.client import LiteLLMClient  # noqa: E402
from pipeline.llm.tokens import import_litellm  # noqa: E402
from tests.scripted_llm import ScriptedModel, _pieces  # noqa: E402


def _logging_queue_empty(litellm) -> bool:
    """Whether litellm's logging executor has no task queued or running (each holds one of its slots)."""
    from litellm.litellm_core_utils.thread_pool_executor import executor

    return executor._pending_slots._value == executor._max_pending_tasks


def read_once(litellm, model: str, api_base: str, logging_on: bool, expected: str) -> float:
    """CPU seconds of this process for one streamed call, until litellm's logging of it is done."""
    litellm.disable_streaming_logging = not logging_on
    client = LiteLLMClient(model, api_base=api_base, api_key="sk-bench", retries=0, structured=False, stream=True)
    began = time.process_time()
    reply = client.complete([{"role": "user", "content": "write the policy"}])
    while not _logging_queue_empty(litellm):
        time.sleep(0.01)
    spent = time.process_time() - began
    if reply.text != expected:
        raise SystemExit(f"the streamed reply came back different ({len(reply.text)} characters, "
                         f"{len(expected)} sent)")
    return spent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pieces", type=int, default=1600, help="word-sized pieces of the streamed reply")
    parser.add_argument("--repeats", type=int, default=3, help="calls of each kind, alternating")
    args = parser.parse_args()
    litellm = import_litellm()
    reply = "def select_action(self, obs):\n" + "    x = 1\n" * max(1, (args.pieces - 3) // 3)  # 3 pieces a line
    print(f"a streamed reply of {len(_pieces(reply)):,} pieces ({len(reply):,} characters), "
          f"{args.repeats} calls of each kind, alternating; CPU of this process per call (best, median)")
    print(f"{'protocol':<10} {'litellm default':>17} {'codearcade':>12} {'ratio':>7} {'median ratio':>13}")
    ratios = []
    with tempfile.TemporaryDirectory() as work, ScriptedModel([{"content": reply}], Path(work)) as server:
        for protocol in ("openai", "anthropic"):
            model, api_base = server.route(protocol)
            spent = {True: [], False: []}
            for _ in range(args.repeats):
                for logging_on in (True, False):
                    spent[logging_on].append(read_once(litellm, model, api_base, logging_on, reply))
            ratio = min(spent[False]) / min(spent[True])
            paired = statistics.median(off / on for on, off in zip(spent[True], spent[False]))
            ratios.append(ratio)
            print(f"{protocol:<10} {min(spent[True]) * 1e3:>14.0f} ms {min(spent[False]) * 1e3:>9.0f} ms "
                  f"{ratio:>7.2f} {paired:>13.2f}")
    print(f"codearcade / litellm's default, worst protocol: {max(ratios):.2f} (target <= 0.6)")


if __name__ == "__main__":
    main()
