"""A store someone else wrote is untrusted input: every verb that reads a run, on a store whose schema is right but
one of whose cells holds anything, answers in a few lines with exit status 0 or 2, never a traceback.

The store is tests/fixtures/greedy_run.duckdb.gz (a five-iteration Pong optimization). Each case changes one cell
of it, chosen by a seeded RNG among the run's JSON settings (``runs.config``: a setting of the wrong type, null, a
list, a huge number, NaN, missing, an unknown key; ``feedback_bands`` with a key too many or too few), the run's own
columns (a missing or unknown game, a starter that points nowhere or does not parse), and the numbers of its
episodes, iterations and calls (NULL, -1, NaN, infinity). Then the verbs run in this process through ``main()``:
``runs``, ``report``, ``blame``, ``view --save``, ``compare A B``, ``doctor``, ``export`` (to a port nobody listens
on: the spans are built from the store before the receiver is reached), ``optimize --resume RUN --iterations N``
(a scripted model that answers with nothing usable: nothing is played) and ``replay`` (for the settings, which are
what it reads; a replay that can read them plays the whole run, so :data:`REPLAYED` of those cases only). It takes
about two minutes: it is marked slow. A value the schema refuses (NOT NULL) is in no store, and skipped.

Before 2026-12-06 ``optimize --resume`` on a run whose ``feedback_bands`` had an unknown key, or whose
``iterations`` was a string, ended in a TypeError's traceback (``pipeline/optimizer/loop.py``); now a recorded
setting that cannot be read is one line naming the run and the setting (``OptimizeConfig.from_record``).
"""

from __future__ import annotations

import gzip
import json
import random
import shutil
import socket
from pathlib import Path

import duckdb
import pytest

from pipeline.cli import main
from store import Store
from tests.conftest import ROOT

FIXTURE = ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz"
SEED = 20261206
CASES = 60
REPLAYED = 6
"""Cases of one setting that ``replay`` also runs on (besides every whole-config case, refused before anything
plays): a replay of a run whose settings read plays all five iterations again (~8 s), so a few, drawn."""

HOSTILE = ["5", "", "x" * 10_000, [], ["1", "2"], {}, {"a": 1}, None, True, -1, 0, 2**70, 1e308, float("nan"),
           float("inf"), -float("inf"), 0.5]
"""Values a recorded setting may be replaced by (json.dumps writes NaN and Infinity, which Python reads back)."""

SETTINGS = ["iterations", "eval_episodes", "workers", "seed", "temperature", "rollout_steps", "eval_max_steps",
            "memory", "token_budget", "rollback", "rollback_fraction", "instruction", "feedback", "max_tokens",
            "game", "model", "api_base", "call_time_limit_s", "episode_time_limit_s", "policy", "rng_key",
            "strategy", "models", "one_life", "observation", "audit_episodes"]

BANDS = [("extra key", lambda b: {**b, "bogus": 1}),
         ("no high", lambda b: {k: v for k, v in b.items() if k != "high"}),
         ("high a text", lambda b: {**b, "high": "lots"}), ("messages a list", lambda b: {**b, "messages": ["x"]}),
         ("templates it cannot fill", lambda b: {**b, "messages": {"low": "{nope}", "medium": "{0}", "high": "{"}}),
         ("bands a list", lambda b: [1, 2]), ("bands null", lambda b: None),
         ("target NaN", lambda b: {**b, "target": float("nan")})]

COLUMNS = [  # (table, column, value): one row of the table changed
    ("runs", "game", None), ("runs", "game", "no-such-game"), ("runs", "game", ""), ("runs", "model", "\x1b[2J"),
    ("runs", "seed", None), ("runs", "seed", -1), ("runs", "status", "weird"), ("runs", "status", None),
    ("runs", "starter_policy_hash", "0" * 64), ("runs", "starter_version_id", "nowhere"),
    ("runs", "package_versions", "[]"),
    ("episodes", "length", None), ("episodes", "length", -1), ("episodes", "length", 2**31 - 1),
    ("episodes", "return", float("nan")), ("episodes", "return", float("inf")), ("episodes", "duration_s", None),
    ("episodes", "seed", None), ("episodes", "seed", -(2**62)), ("episodes", "game", "no-such-game"),
    ("episodes", "end_reason", "weird"), ("episodes", "max_steps", -1), ("episodes", "lives_lost", -1),
    ("iterations", "score", float("nan")), ("iterations", "score", float("-inf")), ("iterations", "score", None),
    ("iterations", "best_version_id", "nowhere"), ("iterations", "policy_version_id", "nowhere"),
    ("iterations", "best_iteration", -1), ("iterations", "train_return", float("nan")),
    ("iterations", "eval_episode_ids", ["nowhere"]), ("candidates", "score", float("nan")),
    ("llm_calls", "input_tokens", -1), ("llm_calls", "cost_usd", float("nan")), ("llm_calls", "latency_s", -1.0),
    ("llm_calls", "reply_hash", "nowhere"), ("policy_versions", "loc", -1),
    ("policy_versions", "source_hash", "nowhere"),
    ("feedback", "score", float("inf")), ("feedback", "stage", "weird"),
]


def _cases() -> list[tuple[str, str, object]]:
    """(kind, what, change) for each case: the known ones first, then a seeded draw over the rest."""
    space: list[tuple[str, str, object]] = [("setting", name, value) for name in SETTINGS for value in HOSTILE]
    space += [("setting", name, "missing") for name in SETTINGS] + [("setting", "no_such_setting", 1)]
    space += [("bands", label, change) for label, change in BANDS]
    space += [("config", "the whole config", text) for text in ("null", "[]", '"x"', "{}", "1e999")]
    space += [("column", f"{table}.{column}", value) for table, column, value in COLUMNS]
    space += [("starter", "a starter that does not parse", "def (:\n"), ("starter", "an empty starter", "")]
    known = [("bands", label, change) for label, change in BANDS] + \
        [("config", "the whole config", text) for text in ("null", "[]", '"x"', "1e999")] + \
        [("setting", "iterations", "5"), ("setting", "instruction", "missing"), ("setting", "seeds", ["a", "b"]),
         ("setting", "policy", {"a": 1}), ("setting", "models", float("-inf"))]
    rng = random.Random(SEED)
    return known + rng.sample([case for case in space if case not in known], CASES - len(known))


def _mutate(store: Store, run: str, case: tuple[str, str, object]) -> None:
    kind, what, change = case
    with store.write() as con:
        if kind in ("setting", "bands", "config"):
            config = json.loads(con.execute("SELECT config FROM runs WHERE run_id = ?", [run]).fetchone()[0])
            if kind == "setting" and change == "missing":
                config.pop(what, None)
            elif kind == "setting":
                config[what] = change
            elif kind == "bands":
                config["feedback_bands"] = change(config["feedback_bands"])
            text = change if kind == "config" else json.dumps(config)
            con.execute("UPDATE runs SET config = ? WHERE run_id = ?", [text, run])
        elif kind == "column":
            table, column = what.split(".")
            con.execute(f'UPDATE {table} SET "{column}" = ? WHERE rowid = (SELECT min(rowid) FROM {table})', [change])
        else:  # the starter's source
            con.execute("UPDATE blobs SET text = ? WHERE hash = (SELECT starter_policy_hash FROM runs)", [change])


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> tuple[Path, str]:
    """The fixture store, upgraded to today's schema once (each case copies it)."""
    path = tmp_path_factory.mktemp("pristine") / "greedy.duckdb"
    with gzip.open(FIXTURE) as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    store = Store(path)
    run = store.query("SELECT run_id FROM runs")[0][0]
    return path, run


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _verbs(run: str, out: Path, model, replayed: bool) -> list[list[str]]:
    verbs = [["runs"], ["runs", "--json"], ["report", run, "--out", out / "report"], ["blame", run],
             ["view", run, "--save", out / "run.rrd"], ["compare", run, f"{run}:best"], ["doctor"],
             ["export", run, "--otlp", f"http://127.0.0.1:{_closed_port()}", "--timeout", "1"],
             ["optimize", "--resume", run, "--iterations", "6", "--model", model.model, "--api-base", model.api_base]]
    return verbs + ([["replay", run]] if replayed else [])


@pytest.mark.slow
def test_every_verb_that_reads_a_run_answers_a_hostile_cell_in_a_few_lines(pristine, tmp_path, scripted, capsys):
    source, run = pristine
    model = scripted(["no suggestion here"])  # a reply nothing is made of: a resumed iteration plays nothing
    cases = _cases()
    settings = [i for i, case in enumerate(cases) if case[0] in ("setting", "bands")]
    replayed = {i for i, case in enumerate(cases) if case[0] == "config"}  # refused before anything plays
    replayed |= set(random.Random(SEED).sample(settings, min(REPLAYED, len(settings))))
    failures = []
    for i, case in enumerate(cases):
        shown = case[1] if callable(case[2]) else f"{case[1]} = {case[2]!r:.60}"
        work = tmp_path / str(i)
        work.mkdir()
        path = work / "s.duckdb"
        shutil.copyfile(source, path)
        try:
            _mutate(Store(path), run, case)
        except duckdb.ConstraintException:  # a value the schema itself refuses (NOT NULL): in no store
            continue
        for argv in _verbs(run, work, model, i in replayed):
            try:
                code = main([str(a) for a in [*argv, "--store", path]])
            except SystemExit as exc:
                code = exc.code
            except BaseException as exc:  # noqa: BLE001 - what the person would have seen as a traceback
                code, _ = "raised", capsys.readouterr()
                failures.append(f"{argv[0]} on {shown}: raised {type(exc).__name__}: {exc!s:.200}")
                continue
            _, err = capsys.readouterr()
            errors = [line for line in err.splitlines() if line.startswith("codearcade: error")]
            # doctor's 1: it found the damage; replay's: the run as changed does not replay as it was played
            allowed = (0, 1, 2) if argv[0] in ("doctor", "replay") else (0, 2)
            if code not in allowed or "Traceback" in err or len(err.splitlines()) > 12 or len(errors) > 1 \
                    or sum(map(len, errors)) > 400 or (code == 2 and not errors):
                failures.append(f"{argv[0]} on {shown}: exit {code}, {err[-300:]!r}")
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures)
