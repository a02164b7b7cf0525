"""Space Invaders: a cannon shoots at descending rows of aliens; three lives.

Everything codearcade knows about the game: environment, actions, the paper's task (training horizon,
evaluation cap, staged feedback bands, instruction), observation hooks and Rerun colours. The policy
scaffold is ``games/scaffolds/space_invaders.py``.
Its ``detect`` gives OCAtari's objects exactly, faster (``games/readers/space_invaders.py``).
"""

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader

ROLLOUT_STEPS = 15       # traced training rollout shown to the optimizer (paper: 15; observations are large)
EVAL_MAX_STEPS = 4000
FEEDBACK = {
    # staged feedback: high >= 1000, medium 500 < score < 1000, low <= 500 (paper)
    "high": 1000,
    "low": 500,
    "target": 1000,
    "messages": {
        "high": "Score {score:g}: excellent. Keep shooting efficiently and dodging alien bullets to survive longer.",
        "medium": "Score {score:g}: {gap:g} below 1000. Time your shots (only one of your bullets can be on "
                  "screen) at aliens above you, and dodge incoming projectiles.",
        "low": "Score {score:g}: {gap:g} below 1000. Shoot when an alien is above you and your previous bullet "
               "is gone, and move out from under alien bullets (positive dy) to keep your three lives.",
    },
}
INSTRUCTION = (
    "You control the cannon in Atari Space Invaders. Improve the trainable methods to shoot down as many "
    "aliens as possible while dodging their bullets."
)

# The authors' published best scores (PAPER.md; mean over trials ± standard error): the paper's Table 1 and
# their follow-up's aggregate (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("paper", "paper", 1200, horizon=15),
    Published("follow-up", "default", 929.0, horizon=15, trials=5, stderr=71.02),
    Published("follow-up", "h1", 570.0, horizon=1, trials=4, stderr=0.0),
)


GAME = Game(
    name="space_invaders",
    env_id="SpaceInvadersNoFrameskip-v4",
    ocatari_name="SpaceInvaders",
    actions=("NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"),
    lives=3,
    restorable_reset=True,
    worst_return=0,  # no reward is negative
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              published=PUBLISHED),
    colours={"Player": (92, 220, 92), "Alien": (255, 90, 220), "Shield": (90, 200, 255), "Bullet": (255, 255, 80),
             "Satellite": (255, 60, 60)},
    scaffold=SCAFFOLDS / "space_invaders.py",
    detect=fast_reader("space_invaders"),
)
