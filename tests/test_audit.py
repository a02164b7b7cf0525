"""The held-out audit (pipeline/optimizer/audit.py): a memorised game is caught, a policy that plays is not.

Under the paper's protocol every seed is the same game, so a policy that replays the moves the competent policy
made in it scores exactly as the competent policy does. The audit plays the best version on seeds the loop never
played under the standard protocol, where the replay falls apart: its run is flagged, the honest run is not.
"""

from __future__ import annotations

import json
import textwrap

import pytest

from games.base import AUDIT_SEED_BASE, AUDIT_SEED_END
from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig, validate_config
from pipeline.optimizer.loop import optimize
from tests.conftest import COMPETENT_REPLY, json_reply, run_main

STEPS = 1000
POLICIES = __import__("pathlib").Path(__file__).parent / "policies"


@pytest.fixture(scope="module")
def competent_moves(tmp_path_factory) -> tuple[list[int], float]:
    """The competent policy's actions in the first STEPS steps of Pong under the paper's protocol, and its return."""
    from store import Store

    store = Store(tmp_path_factory.mktemp("moves") / "moves.duckdb")
    code, _, _ = run_main("eval", POLICIES / "pong_competent.py", "--max-steps", STEPS, "--store", store.path)
    assert code == 0
    actions = [a for (a,) in store.query("SELECT action FROM steps ORDER BY step")]
    [(score,)] = store.query("SELECT return FROM episodes")
    return actions, score


def replay_reply(actions: list[int]) -> str:
    """A suggestion that ignores the game and replays ``actions`` step by step."""
    select = textwrap.dedent(f"""\
        def select_action(self, predicted_ball_y, obs):
            moves = {actions!r}
            self.t = getattr(self, "t", -1) + 1
            return moves[self.t] if self.t < len(moves) else 0
        """)
    return json_reply({"select_action": select})


def _run(store, model, token_budget: int = 8000) -> tuple[object, dict]:
    config = OptimizeConfig(game="pong", iterations=1, eval_max_steps=STEPS, rollout_steps=40, workers=2,
                            token_budget=token_budget, audit_episodes=3, rng_key="audit")
    result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05))
    assert result.status == "finished", result.error
    code, out, _ = run_main("runs", "--json", "--store", str(store.path))
    [summary] = json.loads(out)
    return result, summary


@pytest.mark.slow
def test_a_replayed_game_matches_the_policy_it_copies_and_fails_the_audit(store, scripted, competent_moves):
    actions, competent_score = competent_moves
    result, summary = _run(store, scripted([replay_reply(actions)]))
    it0, it1 = result.iterations
    assert it1.update_status == "accepted" and it1.score == competent_score, "the same game, move for move"
    assert it1.best_iteration == 1 and it1.score > it0.score
    audit = result.audit
    best, starter = audit.row("best", "standard"), audit.row("starter", "standard")
    # sealed: three games drawn when the audit ran, the same for the best and the starter, none a tuning seed
    assert len(set(best["seeds"])) == 3 and best["seeds"] == starter["seeds"], audit.rows
    assert all(AUDIT_SEED_BASE <= seed < AUDIT_SEED_END for seed in best["seeds"])
    assert best["seeds"] != [AUDIT_SEED_BASE + i for i in range(3)], "not the public seeds of earlier versions"
    assert best["tuning_score"] == competent_score and starter["tuning_score"] == it0.score
    # on held-out games under sticky actions the replay is no better than the random starter
    assert best["score"] - starter["score"] < (competent_score - it0.score) / 2, audit.rows
    assert audit.overfit and summary["overfit"] is True and summary["audit_score"] == best["score"]
    episodes = store.query("SELECT kind, count(*), list_sort(list_distinct(list(seed))), bool_and(sticky = 0.25) "
                           "FILTER (WHERE episode_id LIKE '%audit-standard%') FROM episodes WHERE kind = 'audit' "
                           "GROUP BY kind")
    assert episodes == [("audit", 12, sorted(best["seeds"]), True)], "2 versions x 2 protocols x 3 games, as audit"
    prompts = store.query("SELECT b.text FROM llm_calls c JOIN blobs b ON b.hash = c.prompt_hash")
    assert prompts and not any("audit" in text or any(str(seed) in text for seed in best["seeds"])
                               for (text,) in prompts), "no prompt shows the audit or its games"
    code, out, _ = run_main("runs", "--store", str(store.path))
    assert code == 0 and "OVERFIT" in out


@pytest.mark.slow
def test_a_policy_that_plays_keeps_its_gain_on_the_audit(store, scripted):
    result, summary = _run(store, scripted([COMPETENT_REPLY]))
    best, starter = result.audit.row("best", "standard"), result.audit.row("starter", "standard")
    assert best["score"] - starter["score"] >= (best["tuning_score"] - starter["tuning_score"]) / 2, result.audit.rows
    assert not result.audit.overfit and summary["overfit"] is False
    # on demand, again, with more games: the run's audit is replaced, not added to
    first = {row["seeds"][0] for row in result.audit.rows}
    code, out, _ = run_main("audit", "last", "--episodes", "4", "--json", "--store", str(store.path))
    assert code == 0 and len(json.loads(out)["audits"][0]["seeds"]) == 4
    assert store.query("SELECT count(*) FROM audits") == [(4,)]
    seeds = json.loads(out)["audits"][0]["seeds"]
    assert not first & set(seeds), "each audit draws its games afresh"
    returns = _audit_returns(store)
    # reproduced from its seeds: the same games, the same returns, episode for episode
    code, out, _ = run_main("audit", "last", "--seeds", ",".join(map(str, seeds)), "--json", "--store", str(store.path))
    assert code == 0 and json.loads(out)["audits"][0]["seeds"] == seeds
    assert _audit_returns(store) == returns and len(returns) == 16  # 2 versions x 2 protocols x 4 games
    # one seed once a game: a seed twice (the form of a --one-life-continue run's audit) is refused for this run
    code = main(["audit", "last", "--seeds", f"{seeds[0]},{seeds[0]}", "--store", str(store.path)])
    assert code == 2 and _audit_returns(store) == returns
    # an audit of fewer games replaces the earlier one's games too: what kind 'audit' holds is what audits lists
    for games in (2, 1, 3):
        code, out, _ = run_main("audit", "last", "--episodes", str(games), "--json", "--store", str(store.path))
        assert code == 0, out
        listed = store.query("SELECT list_sort(flatten(list(episode_ids))) FROM audits")[0][0]
        kept = [episode for (episode,) in store.query("SELECT episode_id FROM episodes WHERE kind = 'audit' "
                                                      "ORDER BY 1")]
        assert kept == listed and len(kept) == 4 * games, (games, kept)
        assert store.query("SELECT count(*) FROM steps WHERE episode_id NOT IN (SELECT episode_id FROM episodes)"
                           ) == [(0,)], "no steps of a game gone"
        [summary] = json.loads(run_main("runs", "--json", "--store", str(store.path)).stdout)
        assert summary["episodes"] == store.query("SELECT count(*) FROM episodes")[0][0], summary
    assert run_main("doctor", "--store", str(store.path)).returncode == 0
    with store.write() as con:  # an audit whose games are gone is damage the doctor names
        con.execute("DELETE FROM steps WHERE episode_id IN (SELECT unnest(episode_ids) FROM audits LIMIT 1)")
        con.execute("DELETE FROM episodes WHERE episode_id IN (SELECT unnest(episode_ids) FROM audits LIMIT 1)")
    code, out, _ = run_main("doctor", "--store", str(store.path))
    assert code == 1 and "audits whose episodes are missing" in out


@pytest.mark.slow
def test_a_re_audit_stopped_part_way_leaves_the_earlier_audit_whole(store, scripted, monkeypatch, capsys):
    """A re-audit wrote its games under the ids of the earlier audit's (one id per game index): stopped part way
    (a Ctrl-C, an error), the earlier audit's rows named games the new audit had overwritten, with other seeds and
    returns. Each audit's games now have ids of their own; a stopped one deletes those it wrote."""
    import functools

    import pipeline.optimizer.audit as audit_module

    config = OptimizeConfig(game="pong", iterations=1, eval_max_steps=60, rollout_steps=20, workers=1,
                            audit_episodes=2, rng_key="audit")
    model = scripted([COMPETENT_REPLY])
    result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05))
    assert result.status == "finished" and result.audit.rows, result.error

    def audited():
        rows = store.query("SELECT role, protocol, seeds, episode_ids, score FROM audits ORDER BY ALL")
        games = store.query('SELECT episode_id, seed, "return" FROM episodes WHERE kind = \'audit\' ORDER BY ALL')
        return rows, games

    before = audited()
    listed = {episode: seed for _, _, seeds, ids, _ in before[0] for episode, seed in zip(ids, seeds)}
    assert {episode: seed for episode, seed, _ in before[1]} == listed and len(listed) >= 4
    monkeypatch.setattr(audit_module, "EpisodeWriter", functools.partial(audit_module.EpisodeWriter, every_s=0))
    checked = audit_module.checked_outcome
    for stop in (KeyboardInterrupt, RuntimeError):
        for at in (1, len(listed) - 1):  # after the first game is written; at the last, before the rows are
            played = []

            def stopped(spec, outcome, at=at, stop=stop, played=played):
                played.append(spec.episode_id)
                if len(played) > at:
                    raise stop("stopped by the test")
                return checked(spec, outcome)

            monkeypatch.setattr(audit_module, "checked_outcome", stopped)
            with pytest.raises(stop):
                audit_module.audit_run(store, result.run_id, episodes=2)
            assert audited() == before, (stop, at)
            assert not set(played) & set(listed), "the new audit's games have ids of their own"
    # the command line says what is kept
    monkeypatch.setattr(audit_module, "checked_outcome", lambda spec, outcome: (_ for _ in ()).throw(KeyboardInterrupt))
    capsys.readouterr()
    assert main(["audit", result.run_id, "--store", str(store.path)]) == 130
    assert "keeps the audit it had" in capsys.readouterr().err and audited() == before
    monkeypatch.setattr(audit_module, "checked_outcome", checked)
    again = audit_module.audit_run(store, result.run_id, seeds=before[0][0][2])  # the same games, replayed
    rows, games = audited()
    assert [(r[0], r[1], r[2], r[4]) for r in rows] == [(r[0], r[1], r[2], r[4]) for r in before[0]], again.rows
    assert sorted(g[1:] for g in games) == sorted(g[1:] for g in before[1])
    assert not {g[0] for g in games} & set(listed), "the earlier audit's games are gone with its rows"


def _audit_returns(store) -> list[tuple]:
    """Each audit game's id less its audit's token (``.{iteration}.audit-{protocol}.{index}``), seed and result."""
    return store.query("SELECT regexp_replace(episode_id, '^[^.]*|[.][^.]*$', '', 'g') AS game, seed, \"return\", "
                       "length FROM episodes WHERE kind = 'audit' ORDER BY game")


def test_audit_seeds_given_by_hand_are_checked(store, capsys):
    for seeds, fragment in [("5", "5 is not an audit seed"), ("1000001,1000002,1000001", "each seed once"),
                            ("1e6", "not a list of whole numbers"), (str(AUDIT_SEED_END), "is not an audit seed")]:
        with pytest.raises(SystemExit) as exit_:
            main(["audit", "last", "--seeds", seeds, "--store", str(store.path)])
        assert exit_.value.code == 2 and fragment in capsys.readouterr().err, seeds
    assert main(["audit", "last", "--seeds", "1000001,1000002", "--episodes", "3", "--store", str(store.path)]) == 2
    assert "disagree" in capsys.readouterr().err and not store.exists()


def test_audit_seeds_are_drawn_afresh_from_the_whole_range():
    from pipeline.optimizer.audit import draw_audit_seeds

    draws = [draw_audit_seeds(3) for _ in range(200)]
    assert all(len(set(d)) == 3 and all(AUDIT_SEED_BASE <= s < AUDIT_SEED_END for s in d) for d in draws)
    assert len({tuple(d) for d in draws}) == 200, "no two audits play the same games"
    everything = [s for d in draws for s in d]
    # spread over the range, not a block near its start (600 uniform draws: each half holds about 300)
    assert 200 < sum(s < (AUDIT_SEED_BASE + AUDIT_SEED_END) // 2 for s in everything) < 400


def test_tuning_seeds_stay_below_the_audit_seeds():
    with pytest.raises(ValueError, match="1,000,000"):
        validate_config(OptimizeConfig(game="pong", seed=AUDIT_SEED_BASE - 1, eval_episodes=3))
    validate_config(OptimizeConfig(game="pong", seed=AUDIT_SEED_BASE - 3, eval_episodes=3))


# ------------------------------------------------------------------------------------------------ the memoriser
# A policy that never reads the game: it recognises which recorded game it is in by the first PREFIX observations
# and replays the competent policy's moves for it. It holds the tuning game and the three games that were the
# audit's public seeds (AUDIT_SEED_BASE + i under the standard protocol: sticky actions and no-op starts are
# seeded by the game's seed, so the same moves replay the same game). Against those seeds it would pass; against
# the sealed audit's games, which no one knew when it was written, it has nothing to replay.
PREFIX = 30
PUBLIC = [AUDIT_SEED_BASE + i for i in range(3)]
SIGNATURE = textwrap.dedent("""\
    def signature(obs):
        ball, player, enemy = obs.get("Ball"), obs.get("Player"), obs.get("Enemy")
        return (ball and (ball["x"], ball["y"]), player and player["y"], enemy and enemy["y"])
    """)


def recorded_games(tmp_path_factory) -> tuple[list[tuple[list, list[int]]], list[float]]:
    """The competent policy's (first PREFIX observation signatures, moves) on the tuning game and on the public
    seeds under the standard protocol, read back from the store as the policy saw them; and its public returns."""
    from games import get_game, list_widths
    from store import Store
    from store.readers import episode_steps

    store = Store(tmp_path_factory.mktemp("memorised") / "m.duckdb")
    competent = str(POLICIES / "pong_competent.py")
    assert run_main("eval", competent, "--max-steps", str(STEPS), "--store", str(store.path)).returncode == 0
    assert run_main("eval", competent, "--seed", str(PUBLIC[0]), "--episodes", "3", "--sticky", "0.25", "--noop-max",
                    "30", "--max-steps", str(STEPS), "--workers", "2", "--store", str(store.path)).returncode == 0
    namespace: dict = {}
    exec(SIGNATURE, namespace)
    games, public_returns = [], []
    with store.read() as con:
        episodes = con.execute('SELECT episode_id, seed, "return" FROM episodes ORDER BY sticky, seed').fetchall()
        for episode_id, seed, ret in episodes:
            steps = episode_steps(con, episode_id, 0, None, list_widths("pong"), get_game("pong").derive)
            games.append(([namespace["signature"](s["obs"]) for s in steps[:PREFIX]], [s["action"] for s in steps]))
            if seed in PUBLIC:
                public_returns.append(ret)
    assert [seed for _, seed, _ in episodes] == [0, *PUBLIC]
    prefixes = [tuple(sigs) for sigs, _ in games]
    assert len(set(prefixes)) == len(prefixes), "the four games are told apart by their first observations"
    return games, public_returns


def memoriser_reply(games) -> str:
    signature = textwrap.indent(SIGNATURE.replace("def signature(obs):", "def _signature(obs):"), "    ")
    games = [(sigs, "".join(map(str, moves))) for sigs, moves in games]  # a digit a move: Pong's are 0-5
    select = "def select_action(self, predicted_ball_y, obs):\n" + f"    games = {games!r}\n" + signature + \
        textwrap.indent(textwrap.dedent(f"""\
            self.t = t = getattr(self, "t", -1) + 1
            if t == 0:
                self.alive = list(range(len(games)))
            if t < {PREFIX}:
                self.alive = [g for g in self.alive if games[g][0][t] == _signature(obs)]
            if not self.alive:
                return 0
            moves = games[self.alive[0]][1]
            return int(moves[t]) if t < len(moves) else 0
            """), "    ")
    return json_reply({"select_action": select})


@pytest.mark.slow
def test_a_memorised_public_audit_is_caught_by_the_sealed_one(store, scripted, tmp_path_factory):
    games, public_returns = recorded_games(tmp_path_factory)
    result, summary = _run(store, scripted([memoriser_reply(games)]), token_budget=40_000)  # room for its tables
    it0, it1 = result.iterations
    assert it1.update_status == "accepted" and it1.best_iteration == 1 and it1.score > it0.score, it1.detail
    # the sealed audit: games nobody knew when the policy was written; the memoriser has nothing to replay
    sealed = result.audit.row("best", "standard")
    assert not set(sealed["seeds"]) & set(PUBLIC)
    assert result.audit.overfit and summary["overfit"] is True, result.audit.rows
    # the public seeds, replayed on purpose (`audit --seeds`): there it plays the competent policy's games move for
    # move, and passes: an audit whose games can be known in advance would have been memorised
    code, out, _ = run_main("audit", "last", "--seeds", ",".join(map(str, PUBLIC)), "--json", "--store", store.path)
    assert code == 0
    [public] = [row for row in json.loads(out)["audits"] if (row["role"], row["protocol"]) == ("best", "standard")]
    assert public["seeds"] == PUBLIC
    assert public["score"] == pytest.approx(sum(public_returns) / 3), "memorised: the competent policy's returns"
    assert public["overfit"] is False and public["score"] > sealed["score"] + 3, (public, sealed)


def test_a_starter_that_forfeited_its_audit_leaves_the_overfit_check_without_a_reference():
    """The check compares the best's gain over the starter on the tuning games with what is left on the held-out
    games, each against the starter on the same games. A starter that forfeited its audit games has no score
    there, and the check fell back on its tuning score: the best's held-out score (the standard protocol) against
    the starter's paper-protocol one, where the harder protocol alone reads as lost gain. A best at +5 on tuning
    against a starter's -5, which plays -1 on the held-out games (every policy loses points to sticky actions),
    was flagged OVERFIT; one at +9 was cleared. Neither is known: no reference, said so."""
    from pipeline.cli.runs import _audit
    from pipeline.optimizer.audit import AuditResult
    from store.scores import overfit

    assert overfit(5.0, -5.0, -1.0, None) is None, "was True: the held-out best against the tuning starter"
    assert overfit(5.0, -5.0, 9.0, None) is None, "was False"
    assert overfit(5.0, -5.0, None, None) is True, "a best that forfeits its audit is flagged whatever the starter"
    assert overfit(-6.0, -5.0, 0.0, None) is False, "no gain claimed, none to lose"
    assert overfit(5.0, -5.0, -1.0, -8.0) is False and overfit(5.0, -5.0, -1.0, 0.0) is True, "with a reference"
    from store.scores import NO_REFERENCE

    def row(role, iteration, score, forfeit=None, flag=None):
        return {"role": role, "protocol": "standard", "policy_version_id": f"v{iteration}", "iteration": iteration,
                "seeds": [AUDIT_SEED_BASE + i for i in range(3)], "score": score, "score_low": None,
                "score_high": None, "forfeit": forfeit, "tuning_score": 5.0 if iteration else -5.0, "overfit": flag}

    rows = [row("best", 2, -1.0, flag=overfit(5.0, -5.0, -1.0, None)),
            row("starter", 0, None, forfeit="RuntimeError at step 300")]
    result = AuditResult("run", rows)
    lines = result.lines()
    assert result.overfit is None and not any("OVERFIT" in line for line in lines), lines
    assert lines[-1] == f"audit  overfit: {NO_REFERENCE}", lines
    assert _audit({"audit_score": -1.0, "overfit": None}) == "-1 no reference"
    assert _audit({"audit_score": -1.0, "overfit": True}) == "-1 OVERFIT"
    assert _audit({"audit_score": -1.0, "overfit": False}) == "-1"
    assert _audit({"audit_score": None, "overfit": None}) is None, "not audited"
