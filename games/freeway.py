"""Freeway: guide the chicken across ten lanes of traffic, as often as the 2:16 timer allows; no lives.

Everything codearcade knows about the game: environment, actions, the authors' task (``freeway_training.py`` of
ameliakuang/LLM-Game-Playing-Agents), the observation hooks and Rerun colours. The policy scaffold is
``games/scaffolds/freeway.py``.

Observation (the authors' ``trace_envs/freeway.py``): OCAtari reports two chickens; only the left one (player
1, x=44) is ours and enters the observation, as ``Chicken`` (:func:`chicken`). A car's dx is its speed: the
jump of about +-159 px on the step it wraps around the screen edge is folded back into [-80, 80) before it is
stored (:func:`car`). :func:`derive` groups ``Car0 .. Car9`` into ``Cars`` (lane 1 at the top to lane 10).
OCAtari's RAM extractor is right with int64 RAM (a car at RAM x 0 is at x=-3; numpy 1 wrapped it to 253); :func:`detect`
gives its objects exactly, faster (``games/readers/freeway.py``).
A game lasts 2,048 agent steps under any policy.
"""

from operator import itemgetter

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader, numbered_keys, pop_numbered

INSTRUCTION = (
    "In Freeway, you guide a chicken from the bottom of the screen (y~187) to the top (y~0), crossing 10 lanes of traffic. "
    "You score 1 point each time the chicken reaches the top and it resets to the bottom to cross again. "
    "Actions: 0=NOOP (wait), 1=UP (move toward goal), 2=DOWN (move away from goal). "
    "There are 10 lanes of cars at fixed y-positions (top to bottom): y=27, 43, 59, 75, 91, 107, 123, 139, 155, 171. "
    "Top lanes (y=27-91) have cars moving right-to-left (negative dx). Bottom lanes (y=107-171) have cars moving left-to-right (positive dx). "
    "The chicken is at x~44. Cars have width 8, the chicken has width 6. "
    "If hit by a car, the chicken is pushed back one lane (novice difficulty). "
    "The game runs on a ~2 minute timer. Maximize the number of crossings within the time limit. "
    "Key strategy: always be moving UP unless a car is about to collide. Waiting too long wastes time. "
    "Analyze the trace to figure out when the chicken gets hit and optimize gap detection to avoid cars while maintaining forward progress."
)
FEEDBACK = {
    # authors: >= 50 stops training; >= 25 "Great progress"; 0 < r < 25 medium; <= 0 low
    "high": 25,
    "low": 0,
    "target": 50,
    "messages": {
        "high": "Great progress! You're scoring {score:g} crossings on average ({gap:g} below 50). "
                "Keep optimizing gap detection to push higher.",
        "medium": "You're scoring {score:g} crossings on average ({gap:g} below 50). Try to improve gap "
                  "detection and timing to cross more lanes safely. Remember: always be moving UP unless a car "
                  "is directly in the way.",
        "low": "Your score is {score:g} crossings on average. The chicken needs to move UP (action 1) to cross "
               "lanes. Wait with NOOP (action 0) only when a car is about to hit you, otherwise keep moving UP.",
    },
}
ROLLOUT_STEPS = 100      # authors: --horizon 100 (the script's __main__ hard-codes 150)
EVAL_MAX_STEPS = 2500    # authors: 3 episodes x 2,500 steps (a game ends by itself at 2,048)
EVAL_EPISODES = 3


LANE_Y = (27, 43, 59, 75, 91, 107, 123, 139, 155, 171)
"""Car y per lane, lane 1 (top) to lane 10 (bottom). Lanes 1-5 drive left (dx < 0), 6-10 right (dx > 0)."""
PLAYER_ONE_MAX_X = 80
"""The left chicken (player 1, ours) is at x=44; the idle second player's at x=108."""
SPEED_FOLD = 80
"""A car's dx is folded into [-80, 80): the jump of about +-159 px when it wraps around is not its speed."""


def _box(o) -> tuple[int, int, int, int, int, int]:
    """x, y, w, h, dx, dy of an OCAtari object as ints (``games.envs.objects_to_dict``'s rule: ``int()`` only what is
    not already an int)."""
    x, y = o._xy
    w, h = o.wh
    prev = o._prev_xy
    if prev is None:
        px, py = x, y
    else:
        px, py = prev
    if not (x.__class__ is int and y.__class__ is int and w.__class__ is int and h.__class__ is int
            and px.__class__ is int and py.__class__ is int):
        x, y, w, h = int(x), int(y), int(w), int(h)
        px, py = (x, y) if prev is None else (int(px), int(py))
    return x, y, w, h, x - px, y - py


def chicken(o, obs: dict, rows: list | None) -> None:
    """Only player 1's chicken (the left one) enters the observation, as ``Chicken``."""
    x = o._xy[0]
    if x >= PLAYER_ONE_MAX_X:  # player 2's (x 108): nothing else of it is needed
        return
    x, y, w, h, dx, dy = _box(o)
    obs["Chicken"] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
    if rows is not None:
        rows.append(("Chicken", None, "Chicken", x, y, w, h, dx, dy))


_CAR_KEYS = numbered_keys("Car")


def car(o, obs: dict, rows: list | None) -> None:
    """A car as ``Car<n>`` (n = its slot, lane n+1), with the screen wrap folded out of its dx."""
    x, y, w, h, dx, dy = _box(o)
    dx = ((dx + SPEED_FOLD) % (2 * SPEED_FOLD)) - SPEED_FOLD
    # the next free number: the cars numbered so far are Car0 .. Car<n-1>, and the observation holds at most the
    # chicken besides them; a guess from its size, checked, else a scan from 0
    n = len(obs) - 1 if "Chicken" in obs else len(obs)
    if not (0 <= n < len(_CAR_KEYS) and _CAR_KEYS[n] not in obs and (n == 0 or _CAR_KEYS[n - 1] in obs)):
        n = 0
        while (_CAR_KEYS[n] if n < len(_CAR_KEYS) else f"Car{n}") in obs:
            n += 1
    key = _CAR_KEYS[n] if n < len(_CAR_KEYS) else f"Car{n}"
    obs[key] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
    if rows is not None:
        rows.append((key, None, "Car", x, y, w, h, dx, dy))


def top_first(car: dict) -> int:
    """The order of ``Cars``: by y, lane 1 (top) first."""
    return car["y"]


_BY_Y = itemgetter("y")
""":func:`top_first` in C: the sort of every step calls it for every car."""


def derive(obs: dict, lives: int) -> None:
    """The authors' observation, in place: ``Cars``, the cars sorted by y (lane 1, top, first), each
    {x, y, w, h, dx, dy, lane} with lane 1-10, always present. No ``lives``: Freeway has none."""
    cars = pop_numbered(obs, "Car")
    cars.sort(key=_BY_Y)  # stable
    for c in cars:
        y = c["y"]
        c["lane"] = _LANE_OF_Y[y] if 0 <= y < 256 else _nearest_lane(y)
    obs["Cars"] = cars


def derive_space(space) -> None:
    """The Gymnasium space of the observation :func:`chicken`, :func:`car` and :func:`derive` make, from the
    generic one (``games.spaces``)."""
    from games.spaces import COORDINATE, ListOf, ints, with_fields

    chicken_box, _ = space.take("Chicken")
    space.add("Chicken", with_fields(chicken_box, x=(COORDINATE[0], PLAYER_ONE_MAX_X - 1)), optional=True)
    car_box, slots = space.take("Car")
    car_box = with_fields(car_box, dx=(-SPEED_FOLD, SPEED_FOLD - 1), lane=ints(1, len(LANE_Y)))
    space.add("Cars", ListOf(car_box, slots, key=top_first))


def _nearest_lane(y: int) -> int:
    """The lane (1-10) whose y is nearest ``y``; the upper one on a tie."""
    return min(range(len(LANE_Y)), key=lambda i: abs(LANE_Y[i] - y)) + 1


_LANE_OF_Y = tuple(_nearest_lane(y) for y in range(256))
""":func:`_nearest_lane` of every y a car can have, looked up every step instead of computed."""


# The authors' published best scores (PAPER.md; mean over trials ± standard error): their follow-up's aggregate
# (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("follow-up", "h1", 27.93, horizon=1, trials=5, stderr=2.0),
    Published("follow-up", "h100", 27.2, horizon=100, trials=5, stderr=1.58),
)

GAME = Game(
    name="freeway",
    hot_keys=("Chicken", None),  # the steps table's player_x/y follow the chicken; there is no ball
    env_id="FreewayNoFrameskip-v4",
    ocatari_name="Freeway",
    actions=("NOOP", "UP", "DOWN"),
    lives=0,
    restorable_reset=True,
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              eval_episodes=EVAL_EPISODES,
              published=PUBLISHED),
    colours={"Chicken": (252, 252, 84), "Car": (167, 26, 26)},
    object_hooks={"Chicken": chicken, "Car": car},
    detect=fast_reader("freeway"),
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "freeway.py",
)
