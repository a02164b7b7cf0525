"""Runs as people address and list them: references, shortest unique prefixes, labels, the SQL macros, ``runs``.

A *run reference* is what every verb that takes a run accepts, and what the SQL macro ``run(ref)`` accepts, with
one grammar resolved in one place (:data:`RUN_MATCHES_SQL`), tried in this order:

1. a whole run id;
2. ``last`` (the newest run), ``last~N`` (the N-th before it: ``last~1`` is the one before ``last``; ``last~``
   alone is ``last~1``) or ``-N`` (the N-th newest: ``-1`` is ``last``, ``-2`` is ``last~1``), by ``created_at``,
   among the runs a person started: runs a command made for its own use (``runs.made_by``: the evaluations
   ``codearcade compare`` plays of two versions) are not counted, nor is a served run that holds no submission
   (a ``serve`` tried and stopped before the agent submitted: it has nothing to report, blame, view or audit;
   ``serve --resume`` and ``serve --finalize`` count it, and its id names it everywhere), and a verb that acts only
   on some kinds of run (``audit``, ``replay``, ``optimize --resume``: optimizations) counts only those; a verb says
   so when it passed over a newer run;
3. a run's label (``runs.name``, given with ``--name`` or by a batch entry), when one run has it;
4. the start of a run id, in either case, when one run id starts so.

No match, or several at the first level that matches, is an error that says what there is: an ambiguous prefix
lists the candidates by their shortest unique prefixes, as git does. :func:`shortest_prefixes` gives those for
every id (at least :data:`MIN_PREFIX` characters, as git's abbreviations), for printing ids everywhere: ULIDs of
runs started in one afternoon share their first five or six characters, so four never suffice.

In ``codearcade sql`` the same grammar is the macro ``run(ref)`` (the run id; an error when the reference names
none or several) and the table macro ``run_matches(ref)`` (the runs it names, with how): DuckDB macros are
objects of a connection, so :func:`create_sql_macros` makes them, as temporary macros, on each connection that
runs a person's SQL.
"""

from __future__ import annotations

import difflib
import json
import os
import re
import unicodedata
from typing import Any, Iterable

import duckdb

from store.locks import run_is_live

MIN_PREFIX = 8
"""Shortest prefix of a run id printed (a ULID's 8th character changes every second)."""

NAME_MAX = 64
RECENT_FORM = re.compile(r"last(~[0-9]*)?|-[0-9]+")
"""The references by recency: ``last``, ``last~N``, ``-N``."""

UNSUBMITTED_SQL = ("kind = 'serve' AND NOT EXISTS (SELECT 1 FROM candidates c WHERE c.run_id = runs.run_id "
                   "AND c.iteration >= 1)")
"""A condition on a ``runs`` row: a served run that holds no submission (its iteration 0 is the starter, which no
agent submitted; ``store/serve.py``). By recency, such a run is passed over unless a verb asks for it."""

_COUNTED = "made_by IS NULL AND {kinds} AND ({unsubmitted} OR NOT (" + UNSUBMITTED_SQL + "))"
"""Whether a ``runs`` row counts by recency (``last``, ``last~N``, ``-N``): started by a person, of the kinds a
verb acts on, and not a served run without a submission unless the verb asks for those; ``kinds`` and
``unsubmitted`` are SQL filled in by the query or macro that uses it."""
_OF_KINDS = "($kinds IS NULL OR list_contains($kinds, kind))"
COUNTED_SQL = _COUNTED.format(kinds=_OF_KINDS, unsubmitted="$unsubmitted")
""":data:`_COUNTED` with parameters: ``$kinds`` (a list, NULL: any kind) and ``$unsubmitted`` (a boolean), which
:func:`_counting` makes."""


def _counting(kinds: tuple[str, ...] | None = None, unsubmitted: bool = False) -> dict[str, Any]:
    """The parameters of :data:`COUNTED_SQL` (and :data:`RUN_MATCHES_SQL`): only runs of ``kinds`` (None: any)
    count by recency, and served runs without a submission only if ``unsubmitted``."""
    return {"kinds": list(kinds) if kinds else None, "unsubmitted": unsubmitted}


_BODY = r"""
    WITH ref AS (SELECT trim(CAST({ref} AS VARCHAR)) AS text),
    back AS (  -- last / last~N / -N: how many runs back from the newest
        SELECT CASE WHEN text = 'last' THEN 0
                    WHEN text = 'last~' THEN 1
                    WHEN regexp_full_match(text, 'last~[0-9]+') THEN TRY_CAST(text[6:] AS BIGINT)
                    WHEN regexp_full_match(text, '-[0-9]+') THEN TRY_CAST(text[2:] AS BIGINT) - 1
               END AS n FROM ref),
    recent AS (
        SELECT run_id, row_number() OVER (ORDER BY created_at DESC, run_id DESC) - 1 AS n
        FROM runs WHERE {counted}),
    matches AS (
        SELECT r.run_id, 1 AS level, 'id' AS matched FROM runs r, ref WHERE r.run_id = ref.text
        UNION ALL
        SELECT recent.run_id, 2, 'recency' FROM recent, back WHERE recent.n = back.n
        UNION ALL
        SELECT r.run_id, 3, 'name' FROM runs r, ref WHERE r.name = ref.text
        UNION ALL
        SELECT r.run_id, 4, 'prefix' FROM runs r, ref
        WHERE ref.text <> '' AND starts_with(upper(r.run_id), upper(ref.text)))
    SELECT run_id, matched FROM matches WHERE level = (SELECT min(level) FROM matches)
"""
RUN_MATCHES_SQL = _BODY.format(ref="$ref", counted=COUNTED_SQL)
"""The runs a reference (parameter ``$ref``) names, at the first level of the grammar that names any: columns
``run_id`` and ``matched`` (``id``, ``recency``, ``name`` or ``prefix``). By recency, only the runs
:data:`COUNTED_SQL` counts (parameters: :func:`_counting`). The one home of the grammar: the Python resolver runs
it, and the SQL macros are made from it."""

SQL_MACROS: dict[str, tuple[str, str, str]] = {
    "run": (
        "run(ref)",
        "the run id a reference names: a whole id, a unique prefix, last, last~N, -N or a run name; an error when "
        "it names none or several (WHERE run_id = run('last'))",
        # concat, not a cast: a cast of the parameter inside this aggregate query does not bind
        "CREATE TEMP MACRO run(ref) AS (SELECT CASE count(*) WHEN 1 THEN min(run_id) "
        "WHEN 0 THEN error(concat('no run ', ref, ': give a run id, a unique prefix of one, last, "
        "last~N, -N or a run name (SELECT run_id, name FROM run_summary lists them)')) "
        "ELSE error(concat('run ', ref, ' is ambiguous: ', string_agg(run_id, ', ' ORDER BY run_id), "
        "'; give more of the id')) END FROM run_matches(ref))",
    ),
    "run_matches": (
        "run_matches(ref)",
        "table macro: every run a reference names, with how (id, recency, name, prefix): "
        "FROM run_matches('01JD')",
        "CREATE TEMP MACRO run_matches(ref) AS TABLE "
        + _BODY.format(ref="ref", counted=_COUNTED.format(kinds="TRUE", unsubmitted="FALSE")),
    ),
}
"""The macros a person's SQL can use: name -> (signature, one line of help, the statement that makes it). The
table macro comes first in :func:`create_sql_macros`: ``run`` reads it."""


def create_sql_macros(con: duckdb.DuckDBPyConnection) -> None:
    """Make :data:`SQL_MACROS` on ``con`` (temporary macros: they live as long as the connection, and a read-only
    connection may have them)."""
    for name in ("run_matches", "run"):
        con.execute(SQL_MACROS[name][2])


# ------------------------------------------------------------------------------------------------- prefixes


def _common(a: str, b: str) -> int:
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def shortest_prefixes(ids: Iterable[str], min_length: int = MIN_PREFIX) -> dict[str, str]:
    """Each id's shortest prefix that no other id starts with (compared in either case, as references are), at
    least ``min_length`` characters (the whole id when it is shorter)."""
    ordered = sorted(set(ids), key=str.upper)
    upper = [i.upper() for i in ordered]
    out = {}
    for k, run_id in enumerate(ordered):
        shared = max(_common(upper[k], upper[k - 1]) if k else 0,
                     _common(upper[k], upper[k + 1]) if k + 1 < len(ordered) else 0)
        out[run_id] = run_id[:max(min_length, shared + 1)]
    return out


def short_run_ids(con: duckdb.DuckDBPyConnection) -> dict[str, str]:
    """The shortest unique prefix of every run id in the store (:func:`shortest_prefixes`)."""
    return shortest_prefixes(r[0] for r in con.execute("SELECT run_id FROM runs").fetchall())


# ------------------------------------------------------------------------------------------------ resolving


def _where(store: Any) -> str:
    return f" in {store.path}" if store is not None else ""


def _candidate(row: tuple, short: dict[str, str]) -> str:
    run_id, _, kind, game, created, name = row
    label = f" '{name}'" if name else ""
    return f"{short.get(run_id, run_id)}{label} ({kind} {game}, {created:%Y-%m-%d %H:%M})"


def resolve_run_id(con: duckdb.DuckDBPyConnection, text: str, store: Any = None,
                   kinds: tuple[str, ...] | None = None, unsubmitted: bool = False) -> str:
    """The run ``text`` names (the grammar in the module docstring); ValueError, one line, saying what there is
    when it names none or several. ``kinds``: by recency (``last``, ...), only runs of these kinds count;
    ``unsubmitted``: so do served runs without a submission (:data:`UNSUBMITTED_SQL`), which are passed over
    otherwise."""
    ref = text.strip()
    counted = _counting(kinds, unsubmitted)
    rows = con.execute(f"SELECT m.run_id, m.matched, r.kind, r.game, r.created_at, r.name FROM ({RUN_MATCHES_SQL}) m "
                       "JOIN runs r USING (run_id) ORDER BY r.created_at DESC, m.run_id DESC",
                       {"ref": ref, **counted}).fetchall()
    where = _where(store)
    if len(rows) == 1:
        return rows[0][0]
    if not rows:
        (total,) = con.execute("SELECT count(*) FROM runs WHERE made_by IS NULL").fetchone()
        if not total:
            raise ValueError(f"no run {ref or repr(text)}{where}: there are no runs yet; `codearcade eval` or "
                             "`codearcade optimize` makes one")
        if RECENT_FORM.fullmatch(ref):
            total, empty = con.execute(  # empty: the served runs without a submission it does not count
                f"SELECT count(*) FILTER ({COUNTED_SQL}), list(run_id ORDER BY created_at DESC, run_id DESC) "
                f"FILTER (NOT ({COUNTED_SQL})) FROM runs WHERE made_by IS NULL AND {_OF_KINDS}", counted).fetchone()
            kind = f" {' or '.join(kinds)}" if kinds else ""
            held = (f"{total}{kind} runs, last to last~{total - 1} (-1 to -{total})" if total > 1
                    else f"one{kind} run, last (-1)" if total else f"no{kind} run")
            if empty:  # said, or the store seems to have lost the run the person just served
                short = short_run_ids(con)
                held += (f", and {len(empty)} served run{'s' if len(empty) > 1 else ''} without a submission, which "
                         f"{ref} passes over ({', '.join(short.get(r, r) for r in empty[:3])}"
                         f"{' ...' if len(empty) > 3 else ''}: give its id)")
            raise ValueError(f"no{kind} run {ref}{where}: it holds {held}; `codearcade runs` lists them")
        names = [r[0] for r in con.execute("SELECT DISTINCT name FROM runs WHERE name IS NOT NULL").fetchall()]
        near = difflib.get_close_matches(ref, ["last", *names], n=1, cutoff=0.6) if ref else []
        hint = f"; did you mean {near[0]}?" if near else "; `codearcade runs` lists the runs"
        raise ValueError(f"no run {ref or repr(text)}{where}: no run id starts with it and no run is named so{hint}")
    short = short_run_ids(con)
    listed = ", ".join(_candidate(row, short) for row in rows[:6]) + (f" and {len(rows) - 6} more" if len(rows) > 6
                                                                       else "")
    if rows[0][1] == "name":
        raise ValueError(f"{len(rows)} runs are named {ref!r}{where}: {listed}; give one by its id")
    raise ValueError(f"run {ref} is ambiguous{where}: {listed}; give more of the id")


def unsubmitted(con: duckdb.DuckDBPyConnection, run_id: str) -> bool:
    """Whether ``run_id`` is a served run that holds no submission (:data:`UNSUBMITTED_SQL`): nothing to audit or
    finalize, and passed over by ``last`` and its kin."""
    row = con.execute(f"SELECT {UNSUBMITTED_SQL} AS empty FROM runs WHERE run_id = $run", {"run": run_id}).fetchone()
    return bool(row and row[0])


def passed_over(con: duckdb.DuckDBPyConnection, run_id: str, kinds: tuple[str, ...] | None = None,
                unsubmitted: bool = False) -> list[tuple[str, str, bool]]:
    """The runs newer than ``run_id`` that a reference by recency, counting as :func:`resolve_run_id` does with
    ``kinds`` and ``unsubmitted``, passed over to name it: (run id, kind, whether it is a served run without a
    submission), newest first. Runs a command made for its own use (``made_by``) are never named: no one started
    them."""
    return [(r, k, bool(e)) for r, k, e in con.execute(
        f"SELECT run_id, kind, {UNSUBMITTED_SQL} AS empty FROM runs WHERE made_by IS NULL AND created_at > "
        f"(SELECT created_at FROM runs WHERE run_id = $run) AND NOT ({COUNTED_SQL}) "
        "ORDER BY created_at DESC, run_id DESC", {"run": run_id, **_counting(kinds, unsubmitted)}).fetchall()]


MIN_HINTED_PREFIX = 4
"""Shortest text taken for the start of a run id in :func:`references_by_value` (fewer is any run of the year)."""


def references_by_value(con: duckdb.DuckDBPyConnection, texts: Iterable[str]) -> list[tuple[str, str, list[str]]]:
    """For each of ``texts`` (the string values a person's query compares as they are) that is a run reference but
    not a whole run id (``last``, ``last~N``, a label, the start of an id of at least :data:`MIN_HINTED_PREFIX`
    characters): (the text, how it names runs: ``recency``, ``name`` or ``prefix``, the run ids it names).
    ``-N`` is left out: as a value it is far more often a number than a run. What ``codearcade sql`` says when a
    query with ``WHERE run_id = '01JDX3K2'`` finds nothing: the store keeps ids whole, ``run('01JDX3K2')`` names
    the run."""
    found = []
    for text in dict.fromkeys(texts):
        ref = text.strip()
        if not ref or re.fullmatch(r"-[0-9]+", ref):
            continue
        rows = con.execute(RUN_MATCHES_SQL + " ORDER BY run_id", {"ref": ref, **_counting()}).fetchall()
        if not rows or rows[0][1] == "id" or (rows[0][1] == "prefix" and len(ref) < MIN_HINTED_PREFIX):
            continue
        found.append((text, rows[0][1], [r[0] for r in rows]))
    return found


def check_run_name(name: str) -> str:
    """``name`` if it can be a run's label, else ValueError saying what a name may be: it starts with a letter
    (so it is never taken for a run id, whose ULID starts with a digit, nor for ``-N``), has no control characters
    nor leading or trailing spaces, at most :data:`NAME_MAX` characters, and is not ``last`` or ``last~N``."""
    rule = (f"a run name starts with a letter, has at most {NAME_MAX} characters, no control characters and no "
            "leading or trailing spaces, and is not last or last~N")
    if not isinstance(name, str) or not name:
        raise ValueError(f"empty run name; {rule}")
    if (len(name) > NAME_MAX or name != name.strip() or not name[0].isalpha() or RECENT_FORM.fullmatch(name)
            or any(unicodedata.category(c).startswith("C") for c in name)):
        raise ValueError(f"run name {name[:NAME_MAX + 10]!r} cannot be used: {rule}")
    return name


def runs_named(con: duckdb.DuckDBPyConnection, name: str) -> list[str]:
    """The ids of the runs labelled ``name``, oldest first."""
    return [r for (r,) in con.execute("SELECT run_id FROM runs WHERE name = ? ORDER BY created_at", [name]).fetchall()]


# -------------------------------------------------------------------------------------------------- listing


def kind_phrase(kind: str) -> str:
    """``an eval run``, ``a replay run``: a run's kind in a sentence."""
    return f"{'an' if kind[:1] in 'aeiou' else 'a'} {kind} run"


RUN_STATUSES = ("running", "finished", "failed", "interrupted", "budget", "diverged")
"""The statuses ``runs.status`` holds (docs/schema.md says what each means)."""


def shown_status(store_path: str | os.PathLike, run_id: str, status: str) -> str:
    """A run's status as a person is shown it (``runs``, ``report``, ``compare``): a ``running`` run that no live
    process holds (``store/locks.py``) was killed, and is ``interrupted``, as ``doctor`` says too."""
    return "interrupted" if status == "running" and not run_is_live(store_path, run_id) else status


def list_runs(con: duckdb.DuckDBPyConnection, store_path: str | os.PathLike, game: str | None = None,
              kind: str | None = None, status: str | None = None, limit: int | None = None,
              everything: bool = False) -> list[dict[str, Any]]:
    """The ``run_summary`` rows of the runs a person started (``everything``: also those a command made for its own
    use, see ``made_by``), newest first, each with ``short_id`` (its shortest unique prefix). A ``running`` run that
    no live process holds (``store/locks.py``) was killed: it is listed as ``interrupted``, which ``status`` filters
    by too. ``game``, ``kind`` and ``status`` keep the runs with that value; ``limit`` the first so many."""
    cursor = con.execute(
        "SELECT * FROM run_summary WHERE ($game IS NULL OR game = lower($game)) AND ($kind IS NULL OR kind = $kind) "
        "AND ($everything OR made_by IS NULL) ORDER BY created_at DESC, run_id DESC"
        + (" LIMIT $limit" if limit is not None and status is None else ""),
        {"game": game, "kind": kind, "everything": everything,
         **({"limit": limit} if limit is not None and status is None else {})})
    names = [d[0] for d in cursor.description]
    rows = [dict(zip(names, row)) for row in cursor.fetchall()]
    short = short_run_ids(con)
    per_model: dict[str, list[dict[str, Any]]] = {}  # an ensemble's models (view model_stats)
    cursor = con.execute("SELECT * FROM model_stats WHERE run_id IN (SELECT run_id FROM llm_calls GROUP BY run_id "
                         "HAVING count(DISTINCT request_model) > 1) ORDER BY run_id, calls DESC, model")
    columns = [d[0] for d in cursor.description]
    for values in cursor.fetchall():
        stats = dict(zip(columns, values))
        per_model.setdefault(stats.pop("run_id"), []).append(stats)
    last_choice = dict(con.execute(  # an ensemble's latest reason for a model (llm_calls.model_choice)
        "SELECT run_id, arg_max(model_choice, (iteration, coalesce(candidate, 0), created_at)) FROM llm_calls "
        "WHERE model_choice IS NOT NULL GROUP BY run_id").fetchall())
    listed = []
    for row in rows:
        row["status"] = shown_status(store_path, row["run_id"], row["status"])
        if status is not None and row["status"] != status:
            continue
        listed.append({"short_id": short[row["run_id"]], **row,
                       **({"models": per_model[row["run_id"]]} if row["run_id"] in per_model else {}),
                       **({"last_choice": json.loads(last_choice[row["run_id"]])} if row["run_id"] in last_choice
                          else {})})
        if limit is not None and len(listed) >= limit:
            break
    return listed
