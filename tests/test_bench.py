"""The benchmarks in bench/ still run: each one, at its smallest size, ends cleanly and prints its ratios.

Their figures are not checked here (the shared cores are far too noisy for timed assertions); a benchmark
that crashes or stops printing what docs/benchmarks.md quotes is.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import ROOT

SMALLEST = {
    "throughput.py": (["--games", "pong", "--episodes", "1", "--repeats", "1", "--max-steps", "400"],
                      ["eval/stepping", "trace/stepping", "eval/bare", "pong", "targets:", "round trip", "obs bytes",
                       "4 whole games", "ends: "]),
    "step_profile.py": (["--games", "pong", "--repeats", "1", "--max-steps", "200"],
                        ["| emulator |", "| round trip |", "| store write |", "| host (untimed) / bare stepping |",
                         "| game zygote |", "| ROM load¹ |", "| **a command**"]),
    "parallel_eval.py": (["--episodes", "2", "--repeats", "1"], ["codearcade", "bare OCAtari", "target:"]),
    "store_writes.py": (["--episodes", "2"], ["codearcade (2,048 rows)", "ratio (codearcade / default)"]),
    "store_bytes.py": (["--games", "pong", "--episodes", "1", "--warmup", "1", "--max-steps", "200"],
                       ["bytes/step", "after/before", "targets:", "where the bytes go", "pong            traced",
                        "nodes "]),
    "prompt_build.py": (["--steps", "5000", "--repeats", "1"], ["prompt 16k", "prompt 4k"]),
    "lines.py": (["--policies", "tests/policies/pong_competent.py", "--repeats", "1", "--max-steps", "300"],
                 ["+ lines", "pong_competent.py", "time ratio traced+lines / traced"]),
    "rerun_logging.py": (["--games", "pong", "--repeats", "1", "--max-steps", "100"], ["worst log/env ratio"]),
    "prompt_density.py": (["--budgets", "3000"], ["steps/1k before", "competent"]),
    "optimizer_overhead.py": (["--iterations", "2", "--delay", "0.5", "--eval-max-steps", "200"],
                              ["overhead / wall =", "LLM calls", "environment"]),
    "file_view.py": (["--limit", "2000", "--top", "3"], ["files listed:", "readable (os.open O_RDONLY):",
                                                        "below the read rules:", "tests/policies/pong_competent.py"]),
    "proposal_pool.py": (["--calls", "8", "--latency", "0.3", "--repeats", "1", "--greedy-iterations", "1",
                          "--eval-max-steps", "200"], ["best score after k calls", "best score committed after t seconds",
                                                       "rung after 8 calls:", "pool / barrier =",
                                                       "greedy wall / (call + needed episodes) ="]),
    "calibration.py": (["--replicates", "200", "--iqm-replicates", "10"],
                       ["coverage of the true mean", "where t's promise ends", "identical policies called different",
                        "power of Welch's test", "coverage of the true IQM", "| pong | 3 |"]),
    "stream_read.py": (["--pieces", "100", "--repeats", "1"], ["litellm default", "codearcade / litellm's default"]),
    "cascade_steps.py": (["--iterations", "3", "--eval-max-steps", "400", "--screen-steps", "100"],
                         ["steps cheap / baseline =", "same best-so-far curve"]),
}


def test_every_benchmark_is_covered():
    assert sorted(p.name for p in (ROOT / "bench").glob("*.py")) == sorted(SMALLEST)


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(SMALLEST))
def test_benchmark_runs_at_its_smallest_size(script):
    args, expected = SMALLEST[script]
    done = subprocess.run([sys.executable, str(ROOT / "bench" / script), *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    for text in expected:
        assert text in done.stdout, f"{script} no longer prints {text!r}:\n{done.stdout}"
