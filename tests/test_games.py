"""Games as plug-ins: the registry, generic OCAtari games, `codearcade games` and `new`, a game added from
outside the package, and the layering rule (games/ imports nothing above it; nothing above branches on a name)."""

from __future__ import annotations

import ast
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap

import pytest

from games import GAMES, UnknownGameError, get_game
from games.generic import BROKEN_EXTRACTORS
from store import Store
from tests.conftest import ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
UPPER_FLOORS = ("pipeline", "store", "viewers", "tracing")


def _cli(*argv, env=None, cwd=ROOT):
    return subprocess.run([EXE, *argv], cwd=cwd, capture_output=True, text=True, timeout=600, env=env)


def test_games_imports_nothing_from_the_floors_above():
    for path in (ROOT / "games").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            for name in names:
                assert name.split(".")[0] not in UPPER_FLOORS, f"{path.name} imports {name}"


def test_nothing_outside_games_branches_on_a_game_name():
    names = set(GAMES)
    for folder in UPPER_FLOORS:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Compare):
                    for side in [node.left, *node.comparators]:
                        if isinstance(side, ast.Constant) and side.value in names:
                            pytest.fail(f"{path.relative_to(ROOT)}:{node.lineno} compares with the game name "
                                        f"{side.value!r}")


def test_any_spelling_and_generic_games():
    assert get_game("SpaceInvaders") is get_game("space-invaders") is GAMES["space_invaders"]
    riverraid = get_game("Riverraid")
    assert riverraid.status == "generic" and riverraid.env_id == "RiverraidNoFrameskip-v4"
    assert riverraid.actions[:2] == ("NOOP", "FIRE") and riverraid.lives == 4
    with pytest.raises(UnknownGameError, match="Did you mean 'pong'"):
        get_game("pongg")
    with pytest.raises(UnknownGameError, match="time_pilot cannot be played: OCAtari's RAM extractor for it "):
        get_game("time_pilot")
    for broken in BROKEN_EXTRACTORS:  # each reason reads as a sentence after the game's name
        with pytest.raises(UnknownGameError) as refused:
            get_game(broken)
        assert re.fullmatch(rf"{broken} cannot be played: OCAtari(?:'s RAM extractor for it| has no RAM extractor "
                            r"for it) [^']+", str(refused.value)), str(refused.value)


def test_a_generic_game_is_made_from_the_bundled_facts_and_from_its_rom_under_another_ale_py(monkeypatch):
    """A generic game's actions and lives come from ``games/_generic_facts.py`` (``codearcade games`` read ~50 ROMs
    for them, 5 s), and from its ROM when the installed ale-py is not the one they were written with."""
    import games._generic_facts as bundled
    from games import generic

    def no_rom(rom):
        raise AssertionError(f"{rom}'s ROM was loaded")

    monkeypatch.setattr(generic, "read_ale_facts", no_rom)
    generic.generic_game.cache_clear()
    try:
        riverraid = generic.generic_game("riverraid")
        assert (riverraid.actions, riverraid.lives) == bundled.FACTS["riverraid"]
        generic.generic_game.cache_clear()
        monkeypatch.setattr(bundled, "ALE_PY", "0.0.0")
        with pytest.raises(AssertionError, match="riverraid's ROM was loaded"):
            generic.generic_game("riverraid")
    finally:
        generic.generic_game.cache_clear()


@pytest.mark.slow
def test_the_bundled_facts_of_the_generic_games_are_what_their_roms_say(tmp_path):
    """Every entry of ``games/_generic_facts.py`` is what the ROM of the installed ale-py says (the file is what
    ``write_facts`` writes now, every ROM read again)."""
    import ale_py

    from games._generic_facts import ALE_PY
    from games.generic import write_facts

    fix = "run .venv/bin/python -c 'from games.generic import write_facts; write_facts()'"
    assert ALE_PY == ale_py.__version__, f"ale-py {ale_py.__version__} is installed, the facts are of {ALE_PY}: {fix}"
    written = tmp_path / "facts.py"
    write_facts(written)
    bundled = ROOT / "games" / "_generic_facts.py"
    assert written.read_text() == bundled.read_text(), f"a ROM says otherwise: {fix}"


@pytest.mark.slow
@pytest.mark.parametrize("game", ["riverraid", "ms_pacman", "boxing", "tennis"])
def test_generic_game_scaffold_from_new_evaluates_and_stores_steps(tmp_path, game):
    policy = tmp_path / f"{game}.py"
    made = _cli("new", str(policy), "--game", game)
    assert made.returncode == 0, made.stderr
    text = policy.read_text()
    assert f'GAME = "{game}"' in text and "@trace.bundle(trainable=True)" in text and "Player" in text
    assert f"``codearcade eval {policy}``" in text, "its docstring's commands name the file"
    store = tmp_path / "s.duckdb"
    done = _cli("eval", str(policy), "--max-steps", "300", "--trace", "--json", "--store", str(store))
    assert done.returncode == 0, done.stderr
    episode = json.loads(done.stdout)["episodes"][0]
    assert episode["end_reason"] in ("truncated", "terminated")
    s = Store(store)
    steps, nodes = s.query("SELECT (SELECT count(*) FROM steps), (SELECT count(*) FROM nodes)")[0]
    assert steps == episode["length"] and nodes == steps
    assert s.query("SELECT count(*) FROM steps WHERE len(objects) > 0")[0][0] > steps // 2
    again = _cli("new", str(policy), "--game", game)
    assert again.returncode == 2 and "--force" in again.stderr


def test_a_new_scaffold_names_its_own_file(tmp_path, capsys):
    """A copy of a curated scaffold named its original (`codearcade eval games/scaffolds/pong.py`), a surveyed one
    `THIS_FILE`: the commands in a new file's docstring name the file, and a name that cannot sit in a docstring
    (a quote) names POLICY.py there and is shell-quoted in the line that says what to do next."""
    from pipeline.cli import main

    for name, named in (("my pong.py", "POLICY.py"), ("my_pong.py", None), ('we"ird.py', "POLICY.py")):
        policy = tmp_path / name
        assert main(["new", str(policy), "--game", "pong"]) == 0
        said = capsys.readouterr().out
        text = policy.read_text()
        compile(text, name, "exec")
        assert f"``codearcade eval {named or policy}``" in text and "games/scaffolds" not in text, text[:400]
        assert shlex.split(said.split("evaluate it with `")[1].split("`")[0]) == ["codearcade", "eval", str(policy)]


@pytest.mark.slow
def test_games_lists_curated_and_generic():
    listed = json.loads(_cli("games", "--json").stdout)
    by_name = {g["game"]: g for g in listed}
    assert all(by_name[name]["status"] == "curated" for name in GAMES)
    assert by_name["riverraid"]["status"] == "generic" and "time_pilot" not in by_name
    assert by_name["pong"]["rollout_steps"] == 400 and by_name["pong"]["scaffold"] == "games/scaffolds/pong.py"
    assert [g for g in GAMES if by_name[g]["one_life"]] == ["asterix", "breakout", "qbert", "seaquest"]
    assert by_name["riverraid"]["one_life"] is None, "the authors' protocol is known for their games only"


@pytest.mark.slow
def test_a_game_added_from_outside_the_package_plays_through_eval(tmp_path):
    """One module and its scaffold, in a package of their own: no file of codearcade changes."""
    package = tmp_path / "arcade_extra"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "tiny_pong.py").write_text(textwrap.dedent('''
        """Pong under another name, with a derived field: a throw-away game for the plug-in test."""
        from pathlib import Path

        from games import Game, Task


        def derive(obs, lives):
            ball, player = obs.get("Ball"), obs.get("Player")
            obs["ball_above_paddle"] = None if ball is None or player is None else ball["y"] < player["y"]


        GAME = Game(
            name="tiny_pong", env_id="PongNoFrameskip-v4", ocatari_name="Pong",
            actions=("NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"), lives=0,
            task=Task(instruction="Win.", rollout_steps=50, eval_max_steps=300,
                      feedback={"high": 10, "low": 0, "messages": {}}),
            colours={"Ball": (255, 0, 0)}, derive=derive, scaffold=Path(__file__).with_name("tiny_pong_policy.py"),
        )
    '''))
    (package / "tiny_pong_policy.py").write_text(textwrap.dedent('''
        import tracing as trace

        GAME = "tiny_pong"


        @trace.model
        class Policy(trace.Module):
            def __call__(self, obs):
                return self.select_action(obs)

            @trace.bundle(trainable=True)
            def select_action(self, obs):
                if obs["ball_above_paddle"] is None:
                    return 0
                return 2 if obs["ball_above_paddle"] else 3
    '''))
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}", "CODEARCADE_GAME_MODULES": "arcade_extra.tiny_pong"}
    listed = json.loads(_cli("games", "--curated", "--json", env=env).stdout)
    assert "tiny_pong" in {g["game"] for g in listed}
    store = tmp_path / "s.duckdb"
    done = _cli("eval", str(package / "tiny_pong_policy.py"), "--max-steps", "200", "--trace", "--store", str(store),
                env=env)
    assert done.returncode == 0, done.stderr
    s = Store(store)
    assert s.query("SELECT game FROM runs") == [("tiny_pong",)]
    assert s.query("SELECT count(*) FROM steps")[0][0] == 200
    outputs = s.query("SELECT count(*) FROM nodes WHERE output IN ('2', '3')")[0][0]
    assert outputs > 50, "the derived field reached the policy: it moved the paddle"


def test_hot_columns_follow_each_games_player():
    from pipeline.play.rollout import run_episode
    from pipeline.play.spec import EpisodeSpec

    policy = (ROOT / "tests" / "policies" / "freeway_competent.py").read_text()
    outcome = run_episode(EpisodeSpec(episode_id="e", run_id="r", game="freeway", policy_text=policy,
                                      policy_version_id="v", max_steps=60))
    assert get_game("freeway").hot_keys[0] == "Chicken"
    assert outcome.steps.column("player_y").null_count == 0, "Freeway's player is its chicken"
    assert outcome.steps.column("ball_x").null_count == 60


def test_a_game_builds_an_earlier_observation_version_only_where_it_differed():
    """``Game.observing(v)``: the registry's game where version v was built as today (Pong), a variant where it
    differed (Breakout's 8-pixel bricks); a version this codearcade does not know is refused in one line."""
    from games.base import OBSERVATION_VERSION, recorded_observation

    assert get_game("pong").observing(1) is get_game("pong")
    old = get_game("breakout").observing(1)
    assert old.observation == 1 and old.list_widths and old.derive is None
    assert get_game("breakout").observing(None) is get_game("breakout").observing(OBSERVATION_VERSION)
    assert old.observing(1) is old
    with pytest.raises(ValueError, match="registry"):
        old.observing(OBSERVATION_VERSION)
    with pytest.raises(ValueError) as err:
        get_game("breakout").observing(OBSERVATION_VERSION + 1)
    assert "upgrade" in str(err.value) and "\n" not in str(err.value)
    assert recorded_observation({}) == 1 and recorded_observation({"observation": 2}) == 2
