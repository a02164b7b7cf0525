"""Enduro: overtake cars on an endless road (+1 per car passed, -1 per car passing you); no lives.

Everything codearcade knows about the game: environment, actions, the authors' task (``enduro_training.py`` of
ameliakuang/LLM-Game-Playing-Agents), the object detector, the observation and Rerun colours. The policy
scaffold is ``games/scaffolds/enduro.py``.

Detector: OCAtari 2.2.1's Enduro RAM extractor does byte arithmetic that only numpy 1's uint8 semantics make
right (``(~ram[46]) >> 1`` for the player's x, ``(-ram[46]) * -1`` for the road's lateral drift, a signed
byte): under numpy 2, uint8 RAM raises OverflowError at the first curve and int64 RAM gives a player x down to
-49 and car x up to 362. :func:`detect` re-implements that extractor with the numpy-1 results (the signed
bytes done explicitly), OCAtari's own ``Car`` class and its Hungarian matching: it reproduces the authors'
starter score (49) exactly. It reads the RAM only: the released extractor's car x is off by 5-35 px for far
cars and in curves (y is right). The authors apply no correction to it (checked: their
``trace_envs/enduro.py`` copies OCAtari's x, y, w, h and computes ``rel_x``/``rel_y`` from them, nothing else),
so none is applied here either: the boxes are those of the authors' (RAM) observation, not the screen's.

Observation (the authors' ``trace_envs/enduro.py`` with full boxes): :func:`derive` turns ``Car0, Car1, ...``
into ``EnemyCars`` (closest first) with ``rel_x``/``rel_y`` and adds ``nearest_enemy_rel_x/y``. Day 1 ends
the game after 3,328 agent steps when the 200-car quota is not met.
"""

from games.base import SCAFFOLDS, Game, Published, Task, pop_numbered

INSTRUCTION = (
    "In Enduro, you race a car and score by overtaking enemy cars (+1 each) while avoiding being overtaken (-1 each). "
    "Collisions slow the player drastically, causing nearby cars to pass you (multiple -1 penalties). "
    "Actions: 0=NOOP, 1=FIRE(accelerate), 2=RIGHT, 3=LEFT, 4=DOWN(brake), "
    "5=DOWNRIGHT, 6=DOWNLEFT, 7=RIGHTFIRE(steer right+accelerate), 8=LEFTFIRE(steer left+accelerate). "
    "The observation has rel_x (enemy_x - player_x; negative=enemy left, positive=enemy right) "
    "and rel_y (enemy_y - player_y; negative=enemy ahead with smaller y, positive=enemy close/behind with larger y). "
    "EnemyCars list is sorted by proximity (largest y first). "
    "Maintain speed (prefer actions with FIRE: 1, 7, 8) and steer away from close enemies to avoid collisions. "
    "Be precise about which enemies are actual collision threats - over-steering wastes speed and causes worse outcomes."
)
FEEDBACK = {
    # authors: >= 200 stops training (day-1 quota); >= 100 "Great progress"; 0 < r < 100 medium; <= 0 low
    "high": 100,
    "low": 0,
    "target": 200,
    "messages": {
        "high": "Great progress! Net cars passed: {score:g} ({gap:g} short of the 200-car quota for day 1). "
                "Keep accelerating and dodging to avoid collisions (negative reward) and pass more cars.",
        "medium": "Net cars passed: {score:g} ({gap:g} short of 200). Score = cars you overtake minus cars that "
                  "overtake you. Collisions cause negative reward because they slow you down and cars pass you. "
                  "Maintain top speed with FIRE (1) and dodge with RIGHTFIRE (7) / LEFTFIRE (8).",
        "low": "Net cars passed: {score:g} ({gap:g} short of 200). Negative or zero means more cars are "
               "overtaking you than you are passing. You MUST accelerate (FIRE, action 1) and avoid collisions - "
               "each collision slows you and causes cars to pass you (-1 reward each). Steer with RIGHTFIRE (7) / "
               "LEFTFIRE (8).",
    },
}
ROLLOUT_STEPS = 100      # authors: --horizon 100 (also run with 1)
EVAL_MAX_STEPS = 5000    # authors: 1 episode x 5,000 steps (day 1 ends at 3,328 without the quota)
EVAL_EPISODES = 1


PLAYER_HOME = (77, 144)
"""Where relative positions are measured from while the player is not on screen."""
CAR_SLOTS = 7
_ocatari: tuple = ()


def detect(objects: list, ram) -> None:
    """OCAtari 2.2.1's ``ocatari.ram.enduro._detect_objects_ram`` with numpy-1 byte semantics (module docstring).

    ``objects`` is ``extract_ram_info.init_objects("Enduro", False)`` (Player and 7 car slots), updated in place.
    """
    global _ocatari
    if not _ocatari:  # OCAtari loads on first use: the registry imports every game module
        from ocatari.ram.enduro import Car
        from ocatari.vision.utils import match_objects

        _ocatari = (Car, match_objects)
    Car, match_objects = _ocatari
    for o in objects:  # what extract_ram_info.detect_objects_ram does first
        if o:
            o._save_prev()
    v = int(ram[46])  # lateral road offset, a signed byte
    if v & 128:
        px = 77 + ((255 - v) >> 1) + 2   # numpy 1: (~uint8) >> 1
        drift = v - 256                  # numpy 1: (-uint8) * -1 promoted to int16
    else:
        px = 77 - (v >> 1)
        drift = v
    objects[0].xy = px, 89 + int(ram[52])
    speed_term = int(ram[59]) >> 3
    boxes = []
    for i in range(CAR_SLOTS):
        c = int(ram[27 + i])
        if c:
            y = 150 - int(1.2 * ((18 - i) * i) + speed_term * (0.9 ** i))
            if not c & 16:
                x = 87
            elif c & 1:
                x = int((2192 + 7 * y) / 30) + drift
            else:
                x = int((6498 - 23 * y) / 60 + drift)
            boxes.append((x, y, 16, 10))
    match_objects(objects, boxes, 1, CAR_SLOTS, Car)


def closest_first(car: dict) -> int:
    """The order of ``EnemyCars``: largest y (closest) first."""
    return -car["y"]


def derive(obs: dict, lives: int) -> None:
    """The authors' observation, in place: ``EnemyCars``, a list of {x, y, w, h, dx, dy, rel_x, rel_y}
    (relative to the player), largest y (closest) first, ties in OCAtari's slot order, absent when no car is
    visible; ``nearest_enemy_rel_x`` / ``nearest_enemy_rel_y`` of its first car (absent with it). No ``lives``:
    Enduro has none."""
    cars = pop_numbered(obs, "Car")
    if not cars:
        return
    player = obs.get("Player")
    px, py = (player["x"], player["y"]) if player is not None else PLAYER_HOME
    for car in cars:
        car["rel_x"] = car["x"] - px
        car["rel_y"] = car["y"] - py
    cars.sort(key=closest_first)  # stable
    obs["EnemyCars"] = cars
    obs["nearest_enemy_rel_x"] = cars[0]["rel_x"]
    obs["nearest_enemy_rel_y"] = cars[0]["rel_y"]


def derive_space(space) -> None:
    """The Gymnasium space of :func:`derive`'s observation, from the generic one (``games.spaces``). OCAtari
    declares 27 ``Car`` slots; :func:`detect` fills :data:`CAR_SLOTS`."""
    from games.spaces import DELTA, ListOf, ints, with_fields

    car, _ = space.take("Car")
    space.add("EnemyCars", ListOf(with_fields(car, rel_x=DELTA, rel_y=DELTA), CAR_SLOTS, min_length=1,
                                  key=closest_first), optional=True)
    space.add("nearest_enemy_rel_x", ints(*DELTA), optional=True)
    space.add("nearest_enemy_rel_y", ints(*DELTA), optional=True)
    space.together("EnemyCars", "nearest_enemy_rel_x", "nearest_enemy_rel_y")

# The authors' published best scores (PAPER.md; mean over trials ± standard error): their follow-up's aggregate
# (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("follow-up", "h1", 104.0, horizon=1, trials=5, stderr=17.06),
    Published("follow-up", "h100", 71.8, horizon=100, trials=5, stderr=9.38),
)

GAME = Game(
    name="enduro",
    env_id="EnduroNoFrameskip-v4",
    ocatari_name="Enduro",
    actions=("NOOP", "FIRE", "RIGHT", "LEFT", "DOWN", "DOWNRIGHT", "DOWNLEFT", "RIGHTFIRE", "LEFTFIRE"),
    lives=0,
    restorable_reset=True,
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              eval_episodes=EVAL_EPISODES,
              published=PUBLISHED),
    colours={"Player": (192, 192, 192), "Car": (228, 111, 111)},
    detect=detect,
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "enduro.py",
)
