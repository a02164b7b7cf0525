"""``codearcade compare A B``: two runs (``pipeline/optimizer/runs.py``) or two versions played on the same seeds
(``pipeline/play/versus.py``).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Callable

from pipeline.cli.common import (EXIT_OK, CliError, EpisodeProgress, add_settings, add_store, check_output,
                                 command_text, open_store, resolve_run, short_ids, shorten_run_ids, show, show_json)
from pipeline.play.config import CompareConfig
from pipeline.settings import declarations


def add_parser(verbs) -> None:
    """Add ``compare`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "compare",
        help="compare two runs, or play two policy versions on the same seeds and find where they part",
        description="Two runs (each as every verb takes a run: last, last~N, -N, a label, an id or a unique "
        "prefix of one): their learning curves on one plot, the best score each reached within the same LLM "
        "calls, tokens and wall seconds, and the diff of their best versions. Two versions of one game (policy "
        "files, or RUN:VERSION for a version stored in a run: a version id, a unique prefix of one, or 'best'): "
        "both play the same seeds, traced, into the store (two eval runs, which `codearcade runs` and last leave "
        "out), and the report names the first step where their actions differ, with both sides' observations "
        "and node outputs around it. Both also say whether the scores differ beyond the noise (95% intervals: "
        "the paired t of the per-seed differences where both played the same seeds with the same draws, Welch's "
        "t otherwise; store/statistics.py); --audit plays each version on its own audit seeds under "
        "the standard protocol, which is what that needs. Two runs' bests are compared on their held-out games "
        "(`codearcade audit RUN`): each was picked on its tuning episodes, so without both audits their "
        "difference there is shown, not tested.",
        epilog="examples: codearcade compare last~1 last --out cmp/   |   codearcade compare pong_a.py pong_b.py "
        "--max-steps 600 --rerun side_by_side.rrd   |   codearcade compare pong_a.py pong_b.py --audit --episodes 6 "
        "--max-steps 1000   |   codearcade compare last~1:best last:best",
    )
    p.add_argument("a", metavar="A", help="a run (last, last~N, -N, a label, an id or a unique prefix), a policy "
                   "file or RUN:VERSION")
    p.add_argument("b", metavar="B", help="the same kind as A")
    p.add_argument("--out", metavar="DIR", help="write README.md there (and curves.png for two runs); default for "
                   "two runs: ./reports/compare-A-B; two versions: no files")
    add_settings(p, CompareConfig, defaults=True, help_prefix="versions: ")
    p.add_argument("--rerun", metavar="FILE.rrd|URL",
                   help="versions: write a side-by-side Rerun recording of the two episodes of the first seed "
                   "where they part (a .rrd file, or a rerun+http://HOST:PORT/proxy viewer)")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from viewers.compare_report import text_lines, write_report

    if args.rerun and not args.rerun.endswith(".rrd") and not args.rerun.startswith(("rerun://", "rerun+http")):
        raise CliError(f"--rerun {args.rerun}: give a FILE.rrd or a rerun+http://HOST:PORT/proxy url")
    if args.rerun and args.audit:
        raise CliError("--rerun shows the episodes of one seed on both sides; with --audit each side plays its own "
                       "seeds: leave one of them out")
    if args.seed and args.audit:
        raise CliError(f"--seed {args.seed} chooses the seeds both sides play under the paper's protocol; --audit "
                       "draws sealed seeds for each side: leave one of them out")
    if args.out:  # both sides play before the report is written: a folder it cannot make is said first
        check_output(args.out, directory=True)
    if args.rerun and args.rerun.endswith(".rrd"):  # likewise the recording's file
        check_output(args.rerun)
    store = open_store(args)
    given = {name: getattr(args, name) for name in declarations(CompareConfig)}
    if given["workers"] is None:
        given["workers"] = min(args.episodes, os.cpu_count() or 1)
    config = CompareConfig(**given)
    result = compare(store, args.a, args.b, config, progress=lambda line: show(line, file=sys.stderr, flush=True),
                     episodes_progress=EpisodeProgress)
    data = result.as_dict()
    if data["mode"] == "runs":  # the audits that would give the bests' difference a verdict, as a shell takes them
        _audit_commands(store, data)
    for caution in data.get("cautions", ()):  # said first, and on stderr: --json's reader sees it in the data
        show(f"codearcade: warning: {caution}", file=sys.stderr)
    if args.rerun:
        if data["mode"] != "versions":
            raise CliError("--rerun shows two played episodes: it goes with two versions (files or RUN:VERSION)")
        data["rerun"] = _compare_recording(store, data, args.rerun)
    shown = _with_short_ids(store, data)
    out = Path(args.out) if args.out else (
        Path("reports") / f"compare-{shown['runs'][0]['run_id']}-{shown['runs'][1]['run_id']}"
        if data["mode"] == "runs" else None)
    if out is not None:
        data["report"] = str(write_report(data, out))
    if args.json:
        show_json(data, default=str)
        return EXIT_OK
    for line in text_lines(shown):  # terminal-safe already; the tables and the diff span lines
        show(line, multiline=True)
    if data.get("rerun"):
        show(f"side-by-side recording: {data['rerun']}")
    if data.get("report"):
        show(f"report: {data['report']}")
    return EXIT_OK


def _with_short_ids(store, data: dict) -> dict:
    """``data`` with its run ids as a terminal shows them: by their shortest unique prefix in the store (in the
    diff's two header lines too; its body is the policies' code, shown as it is)."""
    short = short_ids(store)
    shown = dict(data)
    if data.get("diff"):
        head, body = data["diff"].split("\n", 2)[:2], data["diff"].split("\n", 2)[2:]
        shown["diff"] = "\n".join([shorten_run_ids(line, short) for line in head] + body)
    if "runs" in data:
        shown["runs"] = [{**r, "run_id": short.get(r["run_id"], r["run_id"])} for r in data["runs"]]
        _audit_commands(store, shown)  # by their short ids
    if "versions" in data:
        shown["versions"] = [{**v, "eval_run": short.get(v["eval_run"], v["eval_run"])} for v in data["versions"]]
    return shown


def _audit_commands(store, data: dict) -> None:
    """Put in ``data``'s difference the ``codearcade audit RUN`` of each run whose best has no held-out score
    (``difference.to_audit``), each run named by the id ``data`` gives it."""
    runs = {r["label"]: r["run_id"] for r in data["runs"]}
    found = data["difference"]
    data["difference"] = {**found, "audit_commands": [command_text(store, "audit", runs[label])
                                                      for label in found.get("to_audit", ())]}


def is_version_ref(text: str, store=None) -> bool:
    """A policy file that exists, or ``RUN:VERSION``; anything else is taken for a run (a reference, as every verb
    takes one). A text with a colon that names a run as it is (a batch run's label, ``pong-ablation:pong,seed=0``)
    is that run."""
    from pathlib import Path

    if Path(text).is_file():
        return True
    if ":" not in text:
        return False
    if store is None or not store.exists():
        return True
    from store.runs import resolve_run_id

    with store.read() as con:
        try:
            resolve_run_id(con, text, store)
        except ValueError:
            return True
    return False


COMPARED_KINDS = ("optimize", "replay", "serve")
"""The kinds of run ``compare A B`` compares: those with iterations (an eval run's policy is a version to play)."""


def compare(store, a: str, b: str, config=None, progress: Callable[[str], None] | None = None,
            episodes_progress: Callable[[int, str], Any] | None = None):
    """Compare ``a`` and ``b``: two runs (``pipeline/optimizer/runs.py``), or two versions
    (``pipeline/play/versus.py``; ``progress`` and ``episodes_progress`` say how its episodes go)."""
    from pathlib import Path

    from pipeline.optimizer.runs import compare_runs
    from pipeline.play.versus import compare_versions
    from tracing.policy_file import PolicyLoadError

    config = config or CompareConfig()
    for ref in (a, b):
        if ref.endswith(".py") and not Path(ref).is_file():
            raise PolicyLoadError(f"policy file '{ref}' does not exist")
    kinds = [is_version_ref(x, store) for x in (a, b)]
    if all(kinds):
        for ref in (a, b):  # RUN:VERSION by recency: say which run it is where a newer one was passed over
            if not Path(ref).is_file():
                resolve_run(store, ref.rpartition(":")[0], verb="compare")
        return compare_versions(store, a, b, config, progress, episodes_progress)
    if not any(kinds):  # `last` and `last~1` count the runs that have iterations, as the other verbs count theirs
        return compare_runs(store, *(resolve_run(store, ref, kinds=COMPARED_KINDS, verb="compare") for ref in (a, b)))
    run, other = (a, b) if not kinds[0] else (b, a)
    raise ValueError(f"{other!r} is a policy version but {run!r} is not (no such file): compare two runs "
                     f"(two run ids) or two versions (policy files or RUN:VERSION, e.g. {run}:best)")


def _compare_recording(store, data: dict, target: str) -> str:
    """Write the side-by-side recording of the first seed whose episodes part (else the first seed), in a
    separate process (this one forks episode workers: Rerun is never loaded here)."""
    import subprocess
    import tempfile
    from pathlib import Path

    episode = next((e for e in data["episodes"] if e["first_divergent_step"] is not None), data["episodes"][0])
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    to = target if target.startswith(("rerun://", "rerun+http")) else str(Path(target).resolve())
    if to != target:  # a file: its folder is made, as --out's is (check_output said before the play that it can be)
        Path(to).parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", suffix=".diff") as diff:
        diff.write(data["diff"])
        diff.flush()
        command = [sys.executable, "-m", "viewers.rerun_compare", "--store", str(store.path.resolve()),
                   "--a", episode["A"]["episode_id"], "--b", episode["B"]["episode_id"], "--to", to,
                   "--diff", diff.name]
        if episode["first_divergent_step"] is not None:
            command += ["--divergent-step", str(episode["first_divergent_step"])]
        done = subprocess.run(command, capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise CliError(f"the side-by-side recording could not be written to {target}: {last}")
    return to
