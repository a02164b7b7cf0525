"""Runs as people address and list them (store/runs.py, store/locate.py): references, shortest unique prefixes,
labels, the SQL macros and parameters, the schema listing, the `runs` listing and the store found without thinking.
Every test works on a real DuckDB file (and real directories for the store's discovery)."""

from __future__ import annotations

import json
import random
import re
import string
from datetime import datetime, timedelta
from pathlib import Path

import duckdb
import pytest

from store import Store, StoreLocation, locate_store
from store.locks import run_lock
from store.migrations import LATEST
from store.runs import (MIN_PREFIX, check_run_name, create_sql_macros, list_runs, resolve_run_id, short_run_ids,
                        shortest_prefixes)
from store.views import TABLES, VIEWS, QueryError, bind_params, run_user_query, schema_listing
from store.writer import finish_run, insert_run, set_run_name
from tests.conftest import old_store

T0 = datetime(2026, 12, 2, 14, 0, 0)
# Four runs of one afternoon: their ULIDs share the first six characters, as real ones do.
RUNS = [  # (run id, minutes after T0, kind, game, name, made_by, config)
    ("01JDX3K2AB7Q000000000000A1", 0, "optimize", "pong", "baseline", None,
     {"strategy": "greedy", "feedback": "staged", "iterations": 3, "policy": "/p/pong_start.py"}),
    ("01JDX3K2AC1M000000000000B2", 5, "optimize", "pong", None, None,
     {"strategy": "beam", "feedback": "rollout", "iterations": 3, "batch": "ablation"}),
    ("01JDX3K9QQ00000000000000C3", 10, "eval", "breakout", None, None, {"policy": "/p/breakout.py"}),
    ("01JDX3KZZZ00000000000000D4", 15, "eval", "pong", None, "compare",
     {"policy": "/tmp/codearcade-compare-x/01JD.abc.py"}),
]


def _add(store: Store, run_id: str, minutes: int, kind: str, game: str, name=None, made_by=None, config=None,
         status="finished") -> None:
    with store.write() as con:
        insert_run(con, run_id, kind, game, config or {}, "# policy\n", "v" * 16, {}, created_at=T0 +
                   timedelta(minutes=minutes), name=name, made_by=made_by)
        if status != "running":
            finish_run(con, run_id, status)


@pytest.fixture
def four(store):
    for run_id, minutes, kind, game, name, made_by, config in RUNS:
        _add(store, run_id, minutes, kind, game, name, made_by, config)
    return store


def _resolve(store: Store, text: str) -> str:
    with store.read() as con:
        return resolve_run_id(con, text, store)


# ------------------------------------------------------------------------------------------------ references

@pytest.mark.parametrize("text, expected", [
    ("01JDX3K2AB7Q000000000000A1", 0),  # a whole id
    ("01JDX3K2AB", 0), ("01jdx3k2ac", 1), ("  01JDX3K9  ", 2),  # unique prefixes, either case, spaces around
    ("last", 2), ("-1", 2),  # the newest run a person started: compare's evaluation (D4) is not counted
    ("last~1", 1), ("last~", 1), ("-2", 1), ("last~2", 0), ("-3", 0),
    ("baseline", 0),  # a label
    ("01JDX3KZ", 3),  # compare's run is still there by its id
])
def test_references(four, text, expected):
    assert _resolve(four, text) == RUNS[expected][0]


@pytest.mark.parametrize("text, expected", [("last", 1), ("-1", 1), ("last~1", 0), ("-2", 0), ("baseline", 0),
                                           ("01JDX3K9", 2)])  # by id or label: what it names, whatever its kind
def test_references_by_recency_count_only_the_kinds_a_verb_acts_on(four, text, expected):
    with four.read() as con:
        assert resolve_run_id(con, text, four, kinds=("optimize",)) == RUNS[expected][0]
        with pytest.raises(ValueError, match=r"no optimize run last~2 .*: it holds 2 optimize runs, last to last~1"):
            resolve_run_id(con, "last~2", four, kinds=("optimize",))


def test_a_verb_that_passes_over_a_newer_run_says_which_it_took(four, capsys):
    from pipeline.cli.common import resolve_run

    assert resolve_run(four, "last", kinds=("optimize",), verb="audit") == RUNS[1][0]
    err = capsys.readouterr().err
    assert re.fullmatch(r"codearcade audit: last is optimize run 01JDX3K2AC\S*, passing over the newer eval run "
                        r"01JDX3K9\S*\n", err), err  # compare's own evaluation (made_by) is not named
    assert resolve_run(four, "last~1", kinds=("optimize",), verb="audit") == RUNS[0][0]
    assert "passing over the newer eval run" in capsys.readouterr().err
    assert resolve_run(four, "baseline", kinds=("optimize",), verb="audit") == RUNS[0][0]
    assert capsys.readouterr().err == "", "a run named, not counted back: nothing passed over"
    assert resolve_run(four, "last") == RUNS[2][0] and capsys.readouterr().err == ""


SERVED = "01JDX3M0SB00000000000000E5"  # a served run with a submission, after the four
UNSUBMITTED = "01JDX3M5UN00000000000000F6"  # a `serve` stopped before any submission, the newest run


def _served(store: Store, submitted: bool = True) -> Store:
    from store.writer import insert_candidate

    _add(store, SERVED, 20, "serve", "pong")
    with store.write() as con:
        insert_candidate(con, dict(run_id=SERVED, iteration=1, candidate=0, strategy="serve",
                                   policy_version_id="v" * 16, update_status="accepted", evaluation="played",
                                   decision="best"))
    _add(store, UNSUBMITTED, 25, "serve", "pong", status="interrupted")
    return store


def test_last_passes_over_a_served_run_without_a_submission_and_says_so(four, capsys):
    # `codearcade serve --mcp` tried and stopped before the agent submitted left an empty run that became `last`
    # for report, blame, view and audit (`audit last` played nothing and exited 0)
    from pipeline.cli.common import resolve_run

    _served(four)
    assert _resolve(four, "last") == SERVED and _resolve(four, "last~1") == RUNS[2][0]
    assert resolve_run(four, "last", verb="report") == SERVED
    assert re.fullmatch(r"codearcade report: last is serve run 01JDX3M0\S*, passing over the newer serve run "
                        r"01JDX3M5\S* \(no submission\)\n", capsys.readouterr().err)
    assert resolve_run(four, "last", kinds=("optimize",), verb="audit") == RUNS[1][0]
    err = capsys.readouterr().err
    assert "serve run 01JDX3M5" in err and "(no submission)" in err and "eval run 01JDX3K9" in err, err
    # serve's own verbs count it: `serve --resume last` opens the run just stopped
    assert resolve_run(four, "last", kinds=("serve",), verb="serve --resume", unsubmitted=True) == UNSUBMITTED
    assert capsys.readouterr().err == ""
    assert _resolve(four, UNSUBMITTED[:10]) == UNSUBMITTED  # by its id it is named as any run
    with four.read() as con:  # and `last` in SQL is the same run
        create_sql_macros(con)
        assert con.execute("SELECT run('last'), run('-2')").fetchone() == (SERVED, RUNS[2][0])


def test_compare_of_versions_by_recency_says_which_run_it_took(four):
    """``compare last:best last:0`` names its runs as every verb does: past a newer served run without a
    submission, one line says which run it took (it said nothing, unlike ``compare last X``)."""
    from tests.conftest import run_main

    _served(four)
    done = run_main("compare", "last:best", "last:0", "--store", str(four.path))
    said = [line for line in done.stderr.splitlines() if "passing over" in line]
    assert said and all(re.fullmatch(r"codearcade compare: last is serve run 01JDX3M0\S*, passing over the newer "
                                     r"serve run 01JDX3M5\S* \(no submission\)", line) for line in said), done.stderr


def test_a_store_whose_only_served_run_holds_no_submission_says_where_it_is(store):
    _add(store, UNSUBMITTED, 25, "serve", "pong", status="interrupted")
    with pytest.raises(ValueError) as refused:
        _resolve(store, "last")
    assert "1 served run without a submission, which last passes over (01JDX3M5" in str(refused.value)


def test_audit_of_a_served_run_without_a_submission_says_so_and_fails(four):
    from tests.conftest import run_main

    _served(four)
    result = run_main("audit", UNSUBMITTED, "--store", four.path)
    assert result.returncode == 2, result
    assert "holds no submission: there is nothing to audit" in result.stderr
    assert "serve --resume 01JDX3M5" in result.stderr


@pytest.mark.parametrize("game, code, said", [
    ("pongg", 2, "did you mean 'pong'?"), ("breakot", 2, "did you mean 'breakout'?"),
    ("qbert", 0, "no runs match"),  # a real game with no runs here: nothing matches, and that is no error
    ("pong", 0, "baseline"), ("PONG", 0, "baseline"), (" Breakout ", 0, "01jdx3k9"),  # spelt as eval takes it
])
def test_runs_of_a_misspelt_game_names_the_game_it_may_mean(four, capsys, game, code, said):
    from pipeline.cli import main

    assert main(["runs", "--game", game, "--store", str(four.path)]) == code
    out, err = capsys.readouterr()
    assert said in (err if code else out).lower(), (out, err)
    if code:
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_an_ambiguous_prefix_lists_the_candidates_by_their_shortest_unique_prefixes(four):
    with pytest.raises(ValueError) as refused:
        _resolve(four, "01JDX3K2A")
    message = str(refused.value)
    assert "\n" not in message and "ambiguous" in message and "give more of the id" in message
    assert "01JDX3K2AB 'baseline' (optimize pong, 2026-12-02 14:00)" in message
    assert "01JDX3K2AC (optimize pong, 2026-12-02 14:05)" in message
    with pytest.raises(ValueError, match="ambiguous"):
        _resolve(four, "01JD")  # four characters never suffice within an afternoon


@pytest.mark.parametrize("text, says", [
    ("last~3", "it holds 3 runs, last to last~2 (-1 to -3)"),
    ("-4", "it holds 3 runs"), ("-0", "it holds 3 runs"),
    ("NOPE", "no run id starts with it and no run is named so; `codearcade runs` lists the runs"),
    ("lsat", "no run id starts with it and no run is named so; did you mean last?"),  # a typo: the nearest
    ("basline", "did you mean baseline?"),
    ("", "no run ''"),
])
def test_a_reference_that_names_nothing_says_what_there_is(four, text, says):
    with pytest.raises(ValueError) as refused:
        _resolve(four, text)
    assert says in str(refused.value) and str(four.path) in str(refused.value)


def test_references_in_an_empty_store_and_one_with_a_single_run(store):
    with store.write():
        pass
    with pytest.raises(ValueError, match="there are no runs yet"):
        _resolve(store, "last")
    _add(store, *RUNS[0][:4])
    with pytest.raises(ValueError, match=r"no run last~1 in .*: it holds one run, last \(-1\);"):
        _resolve(store, "last~1")


def test_a_label_shared_by_two_runs_is_ambiguous(four):
    with four.write() as con:
        set_run_name(con, RUNS[1][0], "baseline")
    with pytest.raises(ValueError, match="2 runs are named 'baseline'.*01JDX3K2AC 'baseline'.*01JDX3K2AB 'baseline'.*give one by its id"):
        _resolve(four, "baseline")
    with four.write() as con:
        set_run_name(con, RUNS[1][0], None)
    assert _resolve(four, "baseline") == RUNS[0][0]


def test_run_names_that_could_be_taken_for_something_else_are_refused(store):
    for good in ("baseline", "ablation/pong feedback=rollout seed=1", "Ω-run"):
        assert check_run_name(good) == good
    for bad in ("last", "last~2", "-1", "01JD", "7up", "", " padded", "a\x1b[31mred", "x" * 65):
        with pytest.raises(ValueError, match="a run name starts with a letter"):
            check_run_name(bad)
    with pytest.raises(ValueError, match="cannot be used"):
        with store.write() as con:
            insert_run(con, "01JDX3K2AB7Q000000000000A1", "eval", "pong", {}, "# p\n", "v" * 16, {}, name="last")
    assert not store.query("SELECT count(*) FROM runs")[0][0], "nothing was stored"


# -------------------------------------------------------------------------------------------------- prefixes

def test_shortest_prefixes_are_unique_minimal_and_at_least_eight_characters():
    rng = random.Random(7)
    alphabet = "0123456789ABCDEFGHJKMNPQRSTVWXYZ"
    base = "01JDX3"
    ids = {base + "".join(rng.choice(alphabet[:4]) for _ in range(rng.randint(4, 20))) for _ in range(300)}
    short = shortest_prefixes(ids)
    for run_id, prefix in short.items():
        assert run_id.startswith(prefix) and len(prefix) >= min(MIN_PREFIX, len(run_id))
        others = [i for i in ids if i != run_id]
        if prefix != run_id:  # a whole id may be the start of another: the id then names itself exactly
            assert not any(i.startswith(prefix) for i in others), (run_id, prefix)
            shorter = prefix[:-1]
            assert len(shorter) < MIN_PREFIX or any(i.startswith(shorter) for i in others), (run_id, prefix)
    assert shortest_prefixes(["01JDX3K2AB7Q", "01jdx3k2ab9z"]) == {"01JDX3K2AB7Q": "01JDX3K2AB7",
                                                                   "01jdx3k2ab9z": "01jdx3k2ab9"}


def test_every_short_id_resolves_back_to_its_run(four):
    with four.read() as con:
        short = short_run_ids(con)
    assert short == {RUNS[0][0]: "01JDX3K2AB", RUNS[1][0]: "01JDX3K2AC", RUNS[2][0]: "01JDX3K9",
                     RUNS[3][0]: "01JDX3KZ"}
    for run_id, prefix in short.items():
        assert _resolve(four, prefix) == run_id


# ------------------------------------------------------------------------------------------------------- sql

def _sql(store: Store, sql: str, params=None) -> list[tuple]:
    return run_user_query(store, sql, params).rows


def test_the_run_macro_resolves_as_every_verb_does(four):
    for text in ("last", "-2", "last~1", "baseline", "01jdx3k9", RUNS[0][0]):
        assert _sql(four, "SELECT run(?)", [text]) == [(_resolve(four, text),)], text
    assert _sql(four, "SELECT kind, game FROM runs WHERE run_id = run('last')") == [("eval", "breakout")]
    assert _sql(four, "SELECT run_id, matched FROM run_matches('01JDX3K2A') ORDER BY run_id") == [
        (RUNS[0][0], "prefix"), (RUNS[1][0], "prefix")]
    with pytest.raises(QueryError, match="run 01JDX3K2A is ambiguous: 01JDX3K2AB7Q"):
        _sql(four, "SELECT * FROM runs WHERE run_id = run('01JDX3K2A')")
    with pytest.raises(QueryError, match="no run NOPE: give a run id"):
        _sql(four, "SELECT run('NOPE')")


def test_parameters_positional_and_named(four):
    assert _sql(four, "SELECT game FROM runs WHERE run_id = run(?) AND seed IS NULL", ["last~1"]) == [("pong",)]
    assert _sql(four, "SELECT $n::INTEGER + 1 AS m, $who AS who", ["who=a=b", "n=41"]) == [(42, "a=b")]
    assert _sql(four, "SELECT ? AS x, $2 AS y", ["k=v", "2"]) == [("k=v", "2")]  # positional: taken as written
    assert _sql(four, "SELECT count(*) FROM runs WHERE created_at > ?", ["2026-12-02 14:04"]) == [(3,)]
    for sql, values, says in (
        ("SELECT ?", [], "the query has 1 parameter (? or $1..), 0 --param values given"),
        ("SELECT ?, ?", ["1"], "has 2 parameters"),
        ("SELECT 1", ["x"], "the query has no parameters"),
        ("SELECT $run", ["x"], "--param 'x' names no parameter of the query ($run)"),
        ("SELECT $run, $it", ["run=last"], "no value for $it; give --param it=VALUE"),
    ):
        with pytest.raises(QueryError) as refused:
            bind_params(sql, values)
        assert says in str(refused.value)


def test_user_sql_stays_read_only_with_the_macros(four, tmp_path):
    """The macros are made before the configuration is locked; a person still cannot make, change or read
    anything else."""
    outside = tmp_path / "outside.csv"
    outside.write_text("a\n1\n")
    for sql in ("CREATE TEMP MACRO run(ref) AS 'x'", "CREATE MACRO m(x) AS x", "DROP MACRO run",
                f"SELECT * FROM read_csv('{outside}')", "SET lock_configuration = false",
                f"ATTACH '{tmp_path / 'x.duckdb'}' AS x", "UPDATE runs SET name = 'x'"):
        with pytest.raises(QueryError):
            _sql(four, sql)
    assert not (tmp_path / "x.duckdb").exists()
    assert _sql(four, "SELECT count(*) FROM runs WHERE name IS NOT NULL") == [(1,)]
    assert _sql(four, "SELECT run('last')") == [(RUNS[2][0],)], "the macro is still the store's"


def test_schema_listing_has_a_line_for_every_table_view_and_macro(four):
    listing = schema_listing(four)
    names = [name for name, _, _ in listing]
    assert names == list(TABLES) + list(VIEWS) + ["run(ref)", "run_matches(ref)", "mean_ci(values)", "iqm_ci(values)",
                                                  "iqm_ci_strata(lists)", "ci_text(ci)", "ci_text(point, low, high)"]
    for name, kind, line in listing:
        assert kind in ("table", "view", "macro", "function") and 20 < len(line) < 160 and "\n" not in line, name
    con = duckdb.connect(str(four.path), read_only=True)  # any DuckDB client sees the same lines
    comments = dict(con.execute("SELECT table_name, comment FROM duckdb_tables()").fetchall())
    con.close()
    assert comments["runs"] == dict((n, line) for n, _, line in listing)["runs"]


def test_schema_doc_documents_the_tables_in_listing_order():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "schema.md").read_text()
    sections = re.findall(r"^## `(\w+)`", doc, re.M)
    assert sections == list(TABLES)


# ---------------------------------------------------------------------------------------------------- listing

def test_runs_listed_newest_first_with_what_tells_them_apart(four):
    with four.read() as con:
        rows = list_runs(con, four.path)
    assert [r["run_id"] for r in rows] == [RUNS[2][0], RUNS[1][0], RUNS[0][0]], "newest first, compare's hidden"
    baseline = rows[-1]
    assert (baseline["short_id"], baseline["name"], baseline["policy"], baseline["strategy"], baseline["feedback"],
            baseline["batch"]) == ("01JDX3K2AB", "baseline", "/p/pong_start.py", "greedy", "staged", None)
    assert (rows[1]["strategy"], rows[1]["feedback"], rows[1]["batch"]) == ("beam", "rollout", "ablation")
    assert rows[0]["strategy"] is None and rows[0]["feedback"] is None, "eval runs have neither"
    with four.read() as con:
        every = list_runs(con, four.path, everything=True)
    assert [r["run_id"] for r in every][0] == RUNS[3][0] and every[0]["made_by"] == "compare"


def test_runs_filters(four):
    _add(four, "01JDX3M00000000000000000E5", 20, "optimize", "pong", status="running")  # killed: no lock held
    _add(four, "01JDX3M10000000000000000F6", 21, "optimize", "pong", status="running")
    with run_lock(four.path, "01JDX3M10000000000000000F6"), four.read() as con:
        def ids(**filters):
            return [r["run_id"][-2:] for r in list_runs(con, four.path, **filters)]

        assert ids() == ["F6", "E5", "C3", "B2", "A1"]
        assert ids(limit=2) == ["F6", "E5"]
        assert ids(game="Pong") == ["F6", "E5", "B2", "A1"] and ids(game="breakout") == ["C3"]
        assert ids(kind="eval") == ["C3"] and ids(kind="eval", everything=True) == ["D4", "C3"]
        assert ids(status="interrupted") == ["E5"] and ids(status="running") == ["F6"]
        assert ids(status="finished", limit=2) == ["C3", "B2"]
        assert ids(game="pong", kind="optimize", status="finished") == ["B2", "A1"]


# -------------------------------------------------------------------------------------------------- migration

def test_migration_8_upgrades_an_old_store(tmp_path):
    """A store at schema 7 with a compare-made eval run gets the label column, the mark and the comments."""
    path = tmp_path / "old.duckdb"
    con = old_store(path, 7)
    for run_id, policy, minutes in (("01JDOLD0000000000000000001", "/home/u/pong.py", 0),
                                    ("01JDOLD0000000000000000002", "/tmp/codearcade-compare-ab12/01JD.v.py", 1)):
        con.execute("INSERT INTO runs (run_id, created_at, kind, game, config, status) VALUES (?, ?, 'eval', 'pong', "
                    "?, 'finished')", [run_id, T0 + timedelta(minutes=minutes), json.dumps({"policy": policy})])
    con.close()
    store = Store(path)
    assert _resolve(store, "last") == "01JDOLD0000000000000000001", "the compare run is not the last"
    assert store.query("SELECT max(version) FROM schema_migrations")[0][0] == LATEST
    assert store.query("SELECT run_id, made_by, name FROM runs ORDER BY run_id") == [
        ("01JDOLD0000000000000000001", None, None), ("01JDOLD0000000000000000002", "compare", None)]
    assert all(line for _, kind, line in schema_listing(store) if kind != "macro")


# ----------------------------------------------------------------------------------------------- discovery

def _project(tmp_path: Path) -> tuple[Path, Path]:
    """tmp/home (for the per-user store) and tmp/work/proj/src/deep, with a store in tmp/work/proj."""
    home = tmp_path / "home"
    deep = tmp_path / "work" / "proj" / "src" / "deep"
    deep.mkdir(parents=True)
    home.mkdir()
    return home, deep


def test_the_store_is_found_by_the_rules_in_order(tmp_path):
    home, deep = _project(tmp_path)
    env = {"HOME": str(home)}
    proj = deep.parent.parent
    user = home / ".local" / "share" / "codearcade" / "codearcade.duckdb"

    found = locate_store(cwd=deep, environ=env, ceiling=tmp_path)
    assert found == StoreLocation(user, "user") and found.surprising
    assert "per-user store" in found.describe() and str(user) in found.describe()

    (tmp_path / "work" / "codearcade.duckdb").write_bytes(b"")
    (proj / "codearcade.duckdb").write_bytes(b"")
    (deep.parent / "codearcade.duckdb").mkdir()  # a directory of that name is not a store
    found = locate_store(cwd=deep, environ=env, ceiling=tmp_path)
    assert found == StoreLocation(proj / "codearcade.duckdb", "parent") and found.surprising, "the nearest"
    assert locate_store(cwd=proj, environ=env, ceiling=tmp_path) == StoreLocation(proj / "codearcade.duckdb", "here")
    assert not locate_store(cwd=proj, environ=env, ceiling=tmp_path).surprising
    assert locate_store(cwd=deep, environ=env, ceiling=proj).rule == "user", "the ceiling is not searched"

    env["CODEARCADE_STORE"] = str(tmp_path / "env.duckdb")
    assert locate_store(cwd=deep, environ=env) == StoreLocation(tmp_path / "env.duckdb", "environment")
    assert locate_store("given.duckdb", cwd=deep, environ=env) == StoreLocation(Path("given.duckdb"), "option")


def test_the_per_user_store_follows_xdg_data_home(tmp_path):
    home, deep = _project(tmp_path)
    data = tmp_path / "data"
    found = locate_store(cwd=deep, environ={"HOME": str(home), "XDG_DATA_HOME": str(data)}, ceiling=tmp_path)
    assert found.path == data / "codearcade" / "codearcade.duckdb"
    relative = locate_store(cwd=deep, environ={"HOME": str(home), "XDG_DATA_HOME": "rel/data"}, ceiling=tmp_path)
    assert relative.path == home / ".local" / "share" / "codearcade" / "codearcade.duckdb", "a relative one is ignored"


def test_a_store_made_without_a_path_is_found_from_a_subdirectory(tmp_path, monkeypatch):
    """Store() takes the process's directory and environment: the first run writes the per-user store (its
    directory made), a project store given once is found from below it, and reads say where they looked."""
    home, deep = _project(tmp_path)
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv("XDG_DATA_HOME", raising=False)
    monkeypatch.delenv("CODEARCADE_STORE", raising=False)
    monkeypatch.chdir(deep)
    if locate_store().rule != "user":
        pytest.skip(f"a codearcade.duckdb above {tmp_path} would be found: {locate_store().path}")
    with pytest.raises(Exception, match=f"no codearcade.duckdb in {deep} or a parent directory, and no per-user"):
        with Store().read():
            pass
    _add(Store(), "01JDX3K2AB7Q000000000000A1", 0, "eval", "pong")
    assert (home / ".local" / "share" / "codearcade" / "codearcade.duckdb").is_file()

    proj = deep.parent.parent
    _add(Store(proj / "codearcade.duckdb"), "01JDX3K9QQ00000000000000C3", 1, "eval", "breakout")
    store = Store()
    assert store.location == StoreLocation(proj / "codearcade.duckdb", "parent")
    assert _resolve(store, "last") == "01JDX3K9QQ00000000000000C3"


def test_run_ids_in_generated_stores_share_six_characters_within_minutes():
    """Why MIN_PREFIX is 8: the store's own ids (ULIDs) made a few minutes apart share their first 6 characters."""
    from pipeline.play.runinfo import new_run_id  # the ids the runs get

    a = new_run_id()
    assert len(a) == 26 and set(a) <= set(string.digits + string.ascii_uppercase)
    other = a[:6] + ("0" if a[6] != "0" else "1") + "Z" * 19  # parts from it at its 7th character, whatever it is
    assert shortest_prefixes([a, other])[a] == a[:MIN_PREFIX]
