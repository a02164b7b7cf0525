"""``codearcade doctor``: check a store's integrity (``store/doctor.py``)."""

from __future__ import annotations

import argparse

from pipeline.cli.common import EXIT_EPISODE_FAILED, EXIT_OK, add_store, open_store, show, show_json


def add_parser(verbs) -> None:
    """Add ``doctor`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "doctor",
        help="check a store's integrity",
        description="Check references, uniqueness and completeness of everything in the store (see store/doctor.py). "
        "Exit 0 when sound (warnings allowed), 1 when damage is found.",
    )
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from store.doctor import check_store, table_counts

    store = open_store(args)
    with store.read(check=False) as con:  # a damaged store is the doctor's business: findings, not an error
        findings = check_store(con, store.path)
        counts = table_counts(con)
    errors = [f for f in findings if not f.warning]
    if args.json:
        show_json({"store": str(store.path), "ok": not errors, "counts": counts,
                   "findings": [{"check": f.check, "warning": f.warning, "rows": [list(map(str, r)) for r in f.rows]}
                                for f in findings]})
    else:
        shown = (f"{'?' if n is None else format(n, ',')} {t}" for t, n in counts.items())
        show(f"{store.path}: " + ", ".join(shown))
        for f in findings:  # a finding quotes the rows it found: a damaged store's text is anyone's
            show(("warning: " if f.warning else "PROBLEM: ") + f.summary())
        show("ok: no damage found" if not errors else f"{len(errors)} kind(s) of damage found")
    return EXIT_OK if not errors else EXIT_EPISODE_FAILED
