"""``codearcade new POLICY.py --game G``: write a policy scaffold."""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import EXIT_OK, CliError, show


def add_parser(verbs) -> None:
    """Add ``new`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "new",
        help="write a policy scaffold for a game",
        description="Write a policy file to start from: a curated game's scaffold, or, for any other game, one "
        "written from the object categories seen in a few hundred random steps and ALE's action meanings, with "
        "one trainable method.",
    )
    p.add_argument("policy", metavar="POLICY.py", help="file to write")
    p.add_argument("--game", required=True, help="the game (`codearcade games` lists them)")
    p.add_argument("--force", action="store_true", help="overwrite POLICY.py if it exists")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from games import get_game
    from games.scaffolding import SURVEY_STEPS, scaffold_text

    path = Path(args.policy)
    if path.exists() and not args.force:
        raise CliError(f"{path} exists; pass --force to overwrite it")
    game = get_game(args.game)
    if game.scaffold is None:
        show(f"surveying {game.name}: {SURVEY_STEPS} random steps...", file=sys.stderr, flush=True)
    path.write_text(scaffold_text(game))
    show(f"wrote {path} ({game.status} game {game.name}); evaluate it with `codearcade eval {path}`, improve it "
         f"with `codearcade optimize {path}`")
    return EXIT_OK
