"""``codearcade games``: the curated games and every game OCAtari reads."""

from __future__ import annotations

import argparse

from pipeline.cli.common import EXIT_OK, show, show_json


def add_parser(verbs) -> None:
    """Add ``games`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "games",
        help="list the games: curated ones and every game OCAtari reads",
        description="List the games codearcade plays: the curated ones (a module in games/ with the authors' "
        "observation conventions, task and scaffold) and every other game OCAtari reads from RAM, played "
        "generically (objects by category, ALE's actions; `codearcade new` writes a scaffold).",
    )
    p.add_argument("--curated", action="store_true", help="only the curated games")
    p.add_argument("--json", action="store_true", help="print the games and their settings as JSON")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from games import GAMES, get_game
    from games.generic import generic_names
    from viewers.tables import format_table

    names = list(GAMES) + ([] if args.curated else [n for n in generic_names() if n not in GAMES])
    rows = []
    for name in names:
        game = get_game(name)
        task = game.task
        rows.append({"game": game.name, "status": game.status, "env_id": game.env_id, "actions": game.n_actions,
                     "lives": game.lives, "rollout_steps": task.rollout_steps, "eval_max_steps": task.eval_max_steps,
                     "one_life": task.one_life_episodes if game.status == "curated" else None,
                     "feedback_high": task.feedback["high"] if game.status == "curated" else None,
                     "feedback_low": task.feedback["low"] if game.status == "curated" else None,
                     "scaffold": str(game.scaffold.relative_to(game.scaffold.parents[2])) if game.scaffold else None})
    if args.json:
        show_json(rows)
        return EXIT_OK
    show(format_table(tuple(rows[0]), [tuple(r.values()) for r in rows], max_width=40, null="-"), multiline=True)
    show(f"({sum(r['status'] == 'curated' for r in rows)} curated, {sum(r['status'] == 'generic' for r in rows)} "
         "generic; `codearcade new POLICY.py --game G` writes a scaffold for any of them)")
    return EXIT_OK
