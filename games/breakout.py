"""Breakout: a paddle returns the ball into six rows of bricks; five lives.

Everything codearcade knows about the game: environment, actions, the paper's task (training horizon,
evaluation cap, staged feedback bands, instruction), observation hooks and Rerun colours. The policy
scaffold is ``games/scaffolds/breakout.py``.

Observation (the authors' ``breakout_training.py`` / ``trace_envs/breakout.py``, with full boxes): ``Player``,
``Ball`` (absent while no ball is in play), the brick rows ``RB OB YB GB AB BB`` as lists of OCAtari's
``Block`` objects, each a run of adjacent bricks (:func:`brick_runs`), and ``lives``. Runs stored before this
convention (observation version 1) split the runs into 8-pixel bricks (:func:`split_bricks`) and replay so.
The environment presses FIRE after reset and after each lost life, and again while no ball has been in play for
a while (:func:`ball_in_play`; under sticky actions a press can be lost: ``games.wrappers.ServeAgain``).
Its ``detect`` gives OCAtari's objects exactly, faster (``games/readers/breakout.py``).
"""

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader

ROLLOUT_STEPS = 300      # traced training rollout shown to the optimizer (paper: 300 for Breakout)
EVAL_MAX_STEPS = 4000
FEEDBACK = {
    # staged feedback: high >= 300, medium 0 < score < 300, low <= 0 (paper)
    "high": 300,
    "low": 0,
    "target": 864,
    "messages": {
        "high": "Score {score:g}: strong play ({gap:g} short of a perfect 864). Keep returning the ball and "
                "aim it at the high-value rows through gaps in the wall.",
        "medium": "Score {score:g}: {gap:g} short of a perfect 864. Return the ball every time and avoid "
                  "losing lives; aim for tunnels toward the red and orange rows (7 points each).",
        "low": "Score {score:g}: the ball is not being returned. Predict where the ball reaches the paddle "
               "plane (y=189), including wall bounces, and move the paddle under it to stop losing lives.",
    },
}
INSTRUCTION = (
    "You control the paddle in Atari Breakout. Improve the trainable methods so the policy never misses the "
    "ball and clears the bricks, highest-value rows first."
)

ROWS = {57: "RB", 63: "OB", 69: "YB", 75: "GB", 81: "AB", 87: "BB"}
"""Brick rows by their y, top to bottom: Red, Orange, Yellow, Green, Aqua, Blue."""
BRICK_WIDTH = 8
WALL_WIDTH = 144
"""Each row is 18 bricks of 8 px (x 8 .. 151)."""


BALL_Y = 101
"""The RAM byte of the ball's height; OCAtari's reader shows no ball when it is 0 or the ball is below the
paddle."""


def ball_in_play(ram) -> bool:
    """Whether a ball is in play in this RAM (uint8, as ALE gives it), by OCAtari's rule for showing ``Ball``."""
    y = int(ram[BALL_Y])  # an int: no uint8 wrap-around
    return y != 0 and y + 9 <= 196


def brick_runs(block, obs: dict, rows: list | None) -> None:
    """The authors' bricks: OCAtari reports each run of adjacent bricks in a row as one ``Block`` (w = 8 * n; a
    full row is one Block, x 8, w 144), and their observation appends each Block unchanged to its row's list.
    The row's list appears with its first Block: OCAtari lists Blocks row by row, top to bottom, left to right,
    so the rows follow ``Player`` and ``Ball`` in the order red to blue, and a cleared row is absent."""
    x, y = block._xy
    w, h = block.wh
    # int() only what is not an int already (games.envs.objects_to_dict's rule): the reader gives ints
    if not (x.__class__ is int and y.__class__ is int and w.__class__ is int and h.__class__ is int):
        x, y, w, h = int(x), int(y), int(w), int(h)
    key = ROWS.get(y)
    if key is None:
        return
    bricks = obs.get(key)
    if bricks is None:
        bricks = obs[key] = []
    if rows is not None:
        rows.append((key, len(bricks), key, x, y, w, h, 0, 0))
    bricks.append({"x": x, "y": y, "w": w, "h": h, "dx": 0, "dy": 0})


def derive(obs: dict, lives: int) -> None:
    """The authors' ``lives`` (they also carry the previous step's ``reward``: docs/observations.md)."""
    obs["lives"] = int(lives)


def split_bricks(block, obs: dict, rows: list | None) -> None:
    """Observation version 1 (runs stored before the authors' conventions): each ``Block`` split into 8-pixel
    bricks, one entry each, in row lists that are always present (``list_widths``); stored as one step-log row
    per run all the same."""
    x, y = (int(v) for v in block._xy)
    key = ROWS.get(y)
    if key is None:
        return
    w, h = (int(v) for v in block.wh)
    bricks = obs[key]
    n = max(1, w // BRICK_WIDTH)
    if rows is not None:
        rows.append((key, len(bricks), key, x, y, n * BRICK_WIDTH, h, 0, 0))
    for i in range(n):
        bricks.append({"x": x + i * BRICK_WIDTH, "y": y, "w": BRICK_WIDTH, "h": h, "dx": 0, "dy": 0})


def derive_space(space) -> None:
    """The Gymnasium space of the rows :func:`brick_runs` makes and of :func:`derive`'s ``lives``, from the generic
    one (``games.spaces``): a row is present while it has bricks, a list of boxes at the row's y, still (dx = dy =
    0), whose width is a multiple of 8 (one brick, or a run of them) up to the wall's."""
    from games.spaces import LIVES, ListOf, OneOf, ints, with_fields

    block, _ = space.take("Block")
    widths = OneOf(range(BRICK_WIDTH, WALL_WIDTH + 1, BRICK_WIDTH))
    for y, key in ROWS.items():
        space.add(key, ListOf(with_fields(block, y=(y, y), w=widths, dx=(0, 0), dy=(0, 0)),
                              WALL_WIDTH // BRICK_WIDTH, min_length=1), optional=True)
    space.add("lives", ints(*LIVES))

# The authors' published best scores (PAPER.md; mean over trials ± standard error): the paper's Table 1 and
# their follow-up's aggregate (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("paper", "paper", 353, horizon=300),
    Published("follow-up", "default", 123.0, horizon=300, trials=5, stderr=57.75),
    Published("follow-up", "h1", 70.6, horizon=1, trials=5, stderr=12.8),
)

GAME = Game(
    name="breakout",
    env_id="BreakoutNoFrameskip-v4",
    ocatari_name="Breakout",
    actions=("NOOP", "FIRE", "RIGHT", "LEFT"),
    lives=5,
    restorable_reset=True,
    worst_return=0,  # no reward is negative
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              one_life_episodes=True,
              published=PUBLISHED),
    colours={"Player": (92, 220, 92), "Ball": (255, 255, 255), "RB": (255, 80, 80), "OB": (255, 150, 60),
             "YB": (230, 220, 60), "GB": (120, 230, 90), "AB": (60, 220, 220), "BB": (90, 120, 255)},
    fire_on_life_loss=True,
    ball_in_play=ball_in_play,
    object_hooks={"Block": brick_runs},
    detect=fast_reader("breakout"),
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "breakout.py",
    earlier_observations={1: {"object_hooks": {"Block": split_bricks}, "derive": None,
                              "list_widths": {key: BRICK_WIDTH for key in ROWS.values()}}},
)
