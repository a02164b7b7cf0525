"""``codearcade new POLICY.py --game G`` / ``--from SCRIPT.py``: write a policy file to start from."""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import EXIT_OK, CliError, show


def add_parser(verbs) -> None:
    """Add ``new`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "new",
        help="write a policy scaffold for a game, or take the policy out of a Trace script",
        description="Write a policy file to start from: a curated game's scaffold, or, for any other game, one "
        "written from the object categories seen in a few hundred random steps and ALE's action meanings, with "
        "one trainable method. With --from, the policy of an existing script instead: a Trace training script "
        "(`import opto.trace as trace`, the environment, the optimizer and the loop around `class Policy`) "
        "becomes a policy file that keeps `Policy`, the definitions it uses and the imports policy code may make.",
    )
    p.add_argument("policy", metavar="POLICY.py", help="file to write")
    p.add_argument("--game", help="the game (`codearcade games` lists them); with --from, written as GAME "
                   "unless the script declares it")
    p.add_argument("--from", dest="source", metavar="SCRIPT.py",
                   help="take the policy out of this script (a Trace training script or another policy file)")
    p.add_argument("--force", action="store_true", help="overwrite POLICY.py if it exists")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import shlex
    from pathlib import Path

    from games import get_game
    from games.scaffolding import SURVEY_STEPS, scaffold_text

    path = Path(args.policy)
    if path.is_dir():  # --force cannot write over a folder: said first (it advised --force, which then failed)
        raise CliError(f"{path} is a folder; give the policy file's path: {path / 'policy.py'}")
    if path.exists() and not args.force:
        raise CliError(f"{path} exists; pass --force to overwrite it")
    if args.source is not None:
        return _from_script(args, path)
    if args.game is None:
        raise CliError("say which game: --game G (`codearcade games` lists them), or take a policy --from SCRIPT.py")
    game = get_game(args.game)
    if game.scaffold is None:
        show(f"surveying {game.name}: {SURVEY_STEPS} random steps...", file=sys.stderr, flush=True)
    path.write_text(scaffold_text(game, path=str(path)))
    typed = shlex.quote(str(path))  # as a shell reads it back
    show(f"wrote {path} ({game.status} game {game.name}); evaluate it with `codearcade eval {typed}`, improve it "
         f"with `codearcade optimize {typed}`")
    return EXIT_OK


def _from_script(args: argparse.Namespace, path) -> int:
    """``new --from``: the policy part of a script, checked as ``eval`` checks a policy file, then written."""
    from pathlib import Path

    from games import get_game
    from tracing.policy_file import inspect_policy, policy_from_script, read_policy_file

    source = Path(args.source)
    if source.resolve() == path.resolve():
        raise CliError(f"--from {source} is the file to write; name another POLICY.py")
    game = get_game(args.game).name if args.game is not None else None
    extracted = policy_from_script(read_policy_file(source, "script"), source.name, game=game)
    info = inspect_policy(extracted.text, path.name)
    if info.game is None:
        raise CliError(f"{source} declares no GAME; say which game it plays with --game G")
    get_game(info.game)
    if not info.trainable:
        show(f"note: {source}'s Policy has no @bundle(trainable=True) method: `optimize` will have nothing to "
             "rewrite", file=sys.stderr)
    path.write_text(extracted.text)
    helpers = f" and {', '.join(extracted.kept)}" if extracted.kept else ""
    left = f"; left out {len(extracted.dropped_imports)} import(s) policy code may not make" \
        if extracted.dropped_imports else ""
    show(f"wrote {path} from {source}: class Policy{helpers} (trainable: "
         f"{', '.join(m.name for m in info.trainable) or 'none'}){left}; evaluate it with "
         f"`codearcade eval {path}`, improve it with `codearcade optimize {path}`")
    return EXIT_OK
