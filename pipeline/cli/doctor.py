"""``codearcade doctor``: check a store's integrity (``store/doctor.py``), and with ``--replay RUN`` re-check a
stored run's scores by replaying its episodes (``pipeline/play/verify.py``)."""

from __future__ import annotations

import argparse

from pipeline.cli.common import (EXIT_EPISODE_FAILED, EXIT_OK, add_store, open_store, resolve_run, short_id, show,
                                 show_json)


def add_parser(verbs) -> None:
    """Add ``doctor`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "doctor",
        help="check a store's integrity",
        description="Check references, uniqueness and completeness of everything in the store (see store/doctor.py). "
        "Exit 0 when sound (warnings allowed), 1 when damage is found.",
    )
    p.add_argument("--replay", metavar="RUN", help="also replay every finished episode of RUN from its recorded "
                   "actions and compare each step's reward, score, flags and lives with what is stored")
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from store.db import StoreDamaged
    from store.doctor import COUNTED_TABLES, Finding, check_store, table_counts

    store = open_store(args)
    try:
        with store.read(check=False) as con:  # a damaged store is the doctor's business: findings, not an error
            findings = check_store(con, store.path)
            counts = table_counts(con)
    except StoreDamaged as exc:  # too damaged to open (cut short): what is known of it, as a finding
        findings = [Finding("damaged file", [(problem,) for problem in exc.problems])]
        counts = dict.fromkeys(COUNTED_TABLES)
    errors = [f for f in findings if not f.warning]
    replayed: list[tuple[str, str | None]] = []
    replay_id = None
    if args.replay and not errors:
        from pipeline.play.verify import replay_run

        replay_id = resolve_run(store, args.replay)
        replayed = replay_run(store, replay_id)
    disagree = [(episode, why) for episode, why in replayed if why is not None]
    if args.json:
        show_json({"store": str(store.path), "ok": not errors and not disagree, "counts": counts,
                   "findings": [{"check": f.check, "warning": f.warning, "rows": [list(map(str, r)) for r in f.rows]}
                                for f in findings],
                   "replayed": [{"episode_id": e, "disagreement": why} for e, why in replayed]})
    else:
        shown = (f"{'?' if n is None else format(n, ',')} {t}" for t, n in counts.items())
        show(f"{store.path}: " + ", ".join(shown))
        for f in findings:  # a finding quotes the rows it found: a damaged store's text is anyone's
            show(("warning: " if f.warning else "PROBLEM: ") + f.summary())
        for episode, why in disagree:
            show(f"PROBLEM: episode {episode} does not replay as stored: {why}")
        if args.replay and replayed:
            show(f"replayed {len(replayed)} episode(s): {len(replayed) - len(disagree)} as stored")
        elif replay_id is not None:  # said, or the silence reads as a run whose episodes all replayed
            show(f"replayed no episode: run {short_id(store, replay_id)} holds no finished episode")
        show("ok: no damage found" if not errors and not disagree else
             f"{len(errors) + bool(disagree)} kind(s) of damage found")
    return EXIT_OK if not errors and not disagree else EXIT_EPISODE_FAILED
