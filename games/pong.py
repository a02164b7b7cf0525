"""Pong: the right paddle against the computer's left paddle; 21 points win.

Everything codearcade knows about the game: environment, actions, the paper's task (training horizon,
evaluation cap, staged feedback bands, instruction), observation hooks and Rerun colours. The policy
scaffold is ``games/scaffolds/pong.py``. its ``detect`` gives OCAtari's objects exactly, faster
(``games/readers/pong.py``).
"""

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader

ROLLOUT_STEPS = 400      # traced training rollout shown to the optimizer (paper: 400 for Pong)
EVAL_MAX_STEPS = 4000    # evaluation cap (paper: ~4000)
FEEDBACK = {
    # staged feedback from the evaluation score: high >= 19, medium 0 < score < 19, low <= 0 (paper)
    "high": 19,
    "low": 0,
    "target": 21,
    "messages": {
        "high": "Score {score:g}: you are winning almost every point ({gap:g} from a perfect 21). "
                "Keep the paddle positioning that works and make returns harder for the opponent.",
        "medium": "Score {score:g}: you win more points than you lose but are {gap:g} from a perfect 21. "
                  "Position the paddle where the ball will arrive so the opponent cannot score.",
        "low": "Score {score:g}: the opponent scores at least as often as you ({gap:g} from a perfect 21). "
               "Work on paddle positioning: predict where the ball crosses x=140 and be there early, "
               "so the opponent cannot score.",
    },
}
INSTRUCTION = (
    "You control the right paddle in Atari Pong. Improve the trainable methods so the policy returns every "
    "ball and wins the game 21 to 0."
)


# The authors' published best scores (PAPER.md; mean over trials ± standard error): the paper's Table 1 and
# their follow-up's aggregate (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("paper", "paper", 21, horizon=400),
    Published("follow-up", "default", 12.0, horizon=400, trials=5, stderr=4.02),
    Published("follow-up", "h1", 5.8, horizon=1, trials=5, stderr=2.46),
)

GAME = Game(
    name="pong",
    env_id="PongNoFrameskip-v4",
    ocatari_name="Pong",
    actions=("NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"),
    action_moves={2: "up", 3: "down", 4: "up", 5: "down"},  # the paddle moves vertically: ALE names it sideways
    lives=0,
    restorable_reset=True,
    worst_return=-21,  # every point lost
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              published=PUBLISHED),
    colours={"Player": (92, 220, 92), "Ball": (255, 255, 255), "Enemy": (255, 140, 40)},
    detect=fast_reader("pong"),
    scaffold=SCAFFOLDS / "pong.py",
)
