"""The authors' published scores as a table, ``published_scores``, filled from the game modules.

A game's published figures are facts of the game and live in its module (``games/<game>.py``,
``Task.published``: ``games.base.Published``). SQL reads them from ``published_scores`` (migration 9), which
:func:`refresh_published` rewrites from the modules when a process first writes to a store (``store/db.py``),
only where the rows differ, so a store shows the figures of the code that last wrote it. ``examples/benchmarks.sql``
joins them to a batch's best scores.
"""

from __future__ import annotations

import duckdb

PUBLISHED_COLUMNS = ("game", "source", "setting", "horizon", "trials", "score", "stderr")
"""The columns of ``published_scores``, in the order of :func:`published_rows`' tuples."""


def published_rows() -> list[tuple]:
    """Every published figure of every game codearcade knows, as :data:`PUBLISHED_COLUMNS` tuples."""
    from games import GAMES  # game modules import only games.base: cheap

    rows: dict[tuple[str, str], tuple] = {}
    for game in GAMES.values():
        for figure in game.task.published:  # one figure per game and setting (the table's key): the first
            rows.setdefault((game.name, figure.setting), (
                game.name, figure.source, figure.setting, figure.horizon, figure.trials, float(figure.score),
                None if figure.stderr is None else float(figure.stderr)))
    return list(rows.values())


def refresh_published(con: duckdb.DuckDBPyConnection) -> bool:
    """Make ``published_scores`` hold exactly :func:`published_rows` (inside the caller's transaction); True if
    it changed anything."""
    columns = ", ".join(PUBLISHED_COLUMNS)
    wanted = published_rows()
    if set(con.execute(f"SELECT {columns} FROM published_scores").fetchall()) == set(wanted):
        return False
    con.execute("DELETE FROM published_scores")
    if wanted:
        con.executemany(f"INSERT INTO published_scores ({columns}) VALUES ({', '.join('?' * len(PUBLISHED_COLUMNS))})",
                        wanted)
    return True
