"""The README and the pages of docs/ hold together: every relative link reaches a file (and a heading, when it names
one), every `codearcade` command their shell blocks show is one the command line accepts as printed, and the
README's test command is the one CI runs. (The SQL examples run for real in tests/test_cli.py, the Gymnasium
example in tests/test_gym_envs.py, the schema's tables and views in tests/test_store.py and tests/test_views.py.)"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from pipeline.cli import build_parser
from tests.conftest import ROOT

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```(\S*)\n(.*?)^```", re.S | re.M)


def _prose(text: str) -> str:
    """The page without its fenced blocks, where `[x](y)` is code, not a link."""
    return FENCE.sub("", text)


def _anchor(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped (hyphens and underscores kept),
    each space a hyphen."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    headings = re.findall(r"^#{1,6} (.+)$", _prose(path.read_text()), re.M)
    return {_anchor(h) for h in headings}


def _links() -> list[tuple[str, str]]:
    """Every relative link (and image) of README.md and docs/*.md: (page, target)."""
    found = []
    for page in PAGES:
        for target in LINK.findall(_prose(page.read_text())):
            if not re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: leave the repository
                found.append((str(page.relative_to(ROOT)), target))
    return found


def test_every_relative_link_reaches_a_file_and_its_heading():
    links = _links()
    # the README links every topic page, and the pages link each other and their pictures
    readme_targets = {target.split("#")[0] for page, target in links if page == "README.md"}
    assert {f"docs/{p.name}" for p in PAGES[1:]} <= readme_targets, "a page of docs/ the README does not link"
    assert sum(target.endswith(".png") for _, target in links) >= 4
    broken = []
    for page, target in links:
        path_part, _, anchor = target.partition("#")
        dest = (ROOT / page).parent / path_part if path_part else ROOT / page
        if not dest.exists():
            broken.append(f"{page}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{page}: {target} (no such heading in {dest.name})")
    assert not broken, "\n".join(broken)


def test_the_link_check_sees_a_broken_link_and_heading(tmp_path):
    """The anchors are GitHub's: a heading with code, a dash and a colon keeps its words and hyphens only."""
    assert _anchor("`runs` — one row per `codearcade eval` or `optimize` run") == \
        "runs--one-row-per-codearcade-eval-or-optimize-run"
    assert _anchor("The evaluation protocol: one life per episode") == "the-evaluation-protocol-one-life-per-episode"
    assert "naming-a-run" in _anchors(ROOT / "docs" / "schema.md")
    assert "nowhere" not in _anchors(ROOT / "docs" / "schema.md")


def _shown_commands() -> list[tuple[str, int, str]]:
    """Every `codearcade ...` command line of a shell block in README.md and docs/*.md (``.venv/bin/codearcade ...``
    after a set-up command's ``&&`` too), and every `$ codearcade ...` of a block that shows a session: (page,
    line, command), a command continued with a backslash joined as the shell joins it."""
    found = []
    for page in PAGES:
        text = page.read_text()
        for block in FENCE.finditer(text):
            prompt = "" if block.group(1) in ("bash", "sh") else "$ "
            first_line = text.count("\n", 0, block.start(2)) + 1
            lines = block.group(2).splitlines()
            k = 0
            while k < len(lines):
                line, at = lines[k], first_line + k
                while line.endswith("\\") and k + 1 < len(lines):
                    k += 1
                    line = line[:-1] + lines[k]
                if prompt == "" and line.startswith(("bash ", ".venv/bin/")):  # set-up && .venv/bin/codearcade ...
                    line = next((part.strip()[len(".venv/bin/"):] for part in line.split(" && ")
                                 if part.strip().startswith(".venv/bin/codearcade ")), line)
                if line.startswith(prompt + "codearcade "):
                    line = line[len(prompt):]
                    while True:  # a query that spans lines: join them until the quotes close
                        try:
                            shlex.split(line, comments=True)
                            break
                        except ValueError:
                            k += 1
                            line += "\n" + lines[k]
                    found.append((str(page.relative_to(ROOT)), at, line))
                k += 1
    return found


def test_every_command_shown_is_accepted_as_printed(capsys):
    """Flags, verbs and choices as the parser knows them: a flag renamed or dropped breaks the page that shows it.
    (Its run ids and files are examples; the commands that run for real are in the tests of each verb.)"""
    commands = _shown_commands()
    pages = {page for page, _, _ in commands}
    assert ("README.md", "codearcade optimize --game pong --iterations 2") in {(p, c) for p, _, c in commands}
    assert len(commands) >= 50 and {"README.md", "docs/cli.md", "docs/games.md", "docs/recordings.md"} <= pages
    parser = build_parser()
    refused = []
    for page, line, command in commands:
        argv = shlex.split(command, comments=True)[1:]
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            refused.append(f"{page}:{line}: {command}\n    {capsys.readouterr().err.strip()}")
            continue
        assert callable(args.handler)
    assert not refused, "\n".join(refused)


def test_a_renamed_flag_would_be_caught(capsys):
    """The check above refuses what the parser refuses: a typo'd flag, an unknown verb, a choice not offered."""
    parser = build_parser()
    for argv in (["eval", "p.py", "--epsiodes", "3"], ["evaluate", "p.py"], ["optimize", "--strategy", "best"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
    assert "did you mean --episodes?" in capsys.readouterr().err


def test_the_readme_shows_the_commands_ci_runs():
    """The set-up commands of the README, byte for byte, and .ci/run runs the test one's steps in its order."""
    readme = (ROOT / "README.md").read_text()
    main_job = "bash scripts/setup.sh && .venv/bin/codearcade optimize --game pong --iterations 2\n"
    tests = "bash scripts/setup.sh && bash scripts/setup_phoenix.sh && .venv/bin/python -m pytest -q\n"
    assert main_job in readme and tests in readme
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    steps = [next(k for k, line in enumerate(ci) if line.startswith(step))
             for step in tests.strip().split(" && ")]
    assert steps == sorted(steps), ci


def test_the_cli_page_shows_every_flag_of_every_verb():
    """docs/cli.md says its table has every verb with its flags: a flag added to a verb and not to the table (a
    reviewer found fourteen: eval's --rng-key and time limits, optimize's --temperature, --max-tokens, ...) fails
    here. Each option of each verb must be shown, by one of its spellings (``-n`` for ``--limit``), in a row of
    that verb; ``--help`` and ``--store``, which every verb takes, are said once below the table."""
    import argparse

    parser = build_parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    shown: dict[str, set[str]] = {}
    for line in (ROOT / "docs" / "cli.md").read_text().splitlines():
        if line.startswith("| `codearcade "):
            command = line.split("` |")[0]
            shown.setdefault(command.split()[2], set()).update(re.findall(r"(?<![\w-])--?[a-z][a-z0-9-]*", command))
    missing = [f"{verb} {'/'.join(action.option_strings)}" for verb, sub in verbs.items() for action in sub._actions
               if action.option_strings and not {"--help", "--store"} & set(action.option_strings)
               and not set(action.option_strings) & shown.get(verb, set())]
    assert not missing, f"docs/cli.md's table does not show: {', '.join(missing)}"
    assert set(verbs) <= set(shown), set(verbs) - set(shown)


def _files_written_on(page: Path) -> dict[str, tuple[int, str | None]]:
    """The policy files a page's shell blocks write before a later command plays them: `codearcade new F` (its
    --game, when given) and a shell redirection `> F.py`: {file: (line, game or None)}."""
    written: dict[str, tuple[int, str | None]] = {}
    text = page.read_text()
    for block in FENCE.finditer(text):
        if block.group(1) not in ("bash", "sh"):
            continue
        first_line = text.count("\n", 0, block.start(2)) + 1
        for k, line in enumerate(block.group(2).splitlines()):
            for name in re.findall(r">\s*([\w./-]+\.py)\b", line):
                written.setdefault(name, (first_line + k, None))
            if line.startswith("codearcade new "):
                words = shlex.split(line, comments=True)
                game = words[words.index("--game") + 1] if "--game" in words else None
                written.setdefault(words[2], (first_line + k, game))
    return written


def _declared_game(path: Path) -> str | None:
    found = re.search(r"^GAME = [\"'](\w+)[\"']", path.read_text(), re.M)
    return found.group(1) if found else None


def test_every_policy_file_a_command_plays_is_there_and_of_its_game():
    """A reader copies the commands in order: a policy file that eval, optimize, compare or serve plays is in the
    repository or written by an earlier command of the same page, and a `--game` beside it is the game the file is
    for (a file that declares another game is refused: `my_policy.py declares GAME = 'riverraid' but --game is
    'pong'`). Files named inside a comment or prose are not commands and are not checked."""
    written = {page: _files_written_on(ROOT / page) for page in {p for p, _, _ in _shown_commands()}}
    wrong = []
    for page, line, command in _shown_commands():
        words = shlex.split(command, comments=True)
        if words[1] not in ("eval", "optimize", "compare", "serve"):
            continue
        game = words[words.index("--game") + 1] if "--game" in words else None
        files = [w for k, w in enumerate(words[2:], 2) if w.endswith(".py") and not words[k - 1].startswith("-")]
        for name in files:
            if (ROOT / name).is_file():
                declared = _declared_game(ROOT / name)
            elif name in written[page] and written[page][name][0] < line:
                declared = written[page][name][1]
            else:
                wrong.append(f"{page}:{line}: {name} is neither in the repository nor written before on the page")
                continue
            if game and declared and game != declared:
                wrong.append(f"{page}:{line}: {name} is a {declared} policy, played with --game {game}")
    assert not wrong, "\n".join(wrong)


def test_the_ranges_docs_cli_states_are_the_declared_ones():
    """docs/cli.md's paragraph on ranges quotes each maximum: each is read from the constant it is declared by, so
    a maximum changed in code and not on the page (or the other way round) fails here."""
    from pipeline.optimizer.config import MAX_CANDIDATES, MAX_ITERATIONS, MAX_REPLY_TOKENS
    from pipeline.play.config import MAX_EPISODES, MAX_NOOPS
    from pipeline.settings import MAX_STEPS, MAX_TIME_LIMIT_S

    page = " ".join((ROOT / "docs" / "cli.md").read_text().split())
    stated = {"games to play at most {:,}": MAX_EPISODES, "no-ops {:,}": MAX_NOOPS, "iterations {:,}": MAX_ITERATIONS,
              "`--screen-steps`) {:,}": MAX_STEPS, "`--max-tokens` {:,}": MAX_REPLY_TOKENS,
              "`--candidates` {:,}": MAX_CANDIDATES, "a week ({:,} s)": MAX_TIME_LIMIT_S}
    for phrase, value in stated.items():
        assert phrase.format(value) in page, f"docs/cli.md should say {phrase.format(value)!r}"
    assert MAX_TIME_LIMIT_S == 7 * 86_400, "the page calls it a week"
