"""Q*bert: hop on the pyramid's 21 cubes to change their colour, avoiding Coily and the balls; four lives.

Everything codearcade knows about the game: environment, actions, the authors' task (``qbert_training.py`` of
ameliakuang/LLM-Game-Playing-Agents), the observation and Rerun colours. The policy scaffold is
``games/scaffolds/qbert.py``.

Observation (the authors' ``trace_envs/qbert.py`` with full boxes): cubes are left out, as the authors do
(``object_hooks`` maps ``Cube`` to ``None``: they are dropped before they are stored, as OCAtari gives their fixed
corners, not their colours; see :data:`CUBES`). :func:`derive` groups the rest into ``Enemies`` (Coily, PurpleBall,
RedBall), ``Friendlies`` (GreenBall, Sam: OCAtari's slot order, as the authors list them) and ``Disks`` and drops
OCAtari's off-screen garbage: while Q*bert falls or is between lives the extractor reports y = RAM[33] - 52 (-52..-35),
and a GreenBall can come with x up to 319 (stale RAM). OCAtari 2.2.1 declares ``RedBall`` but never creates one: red
balls are not reported. Its extractor keeps state in module globals (``init_objects`` resets it; each
environment keeps its own copy: ``games.envs.ObjectObservation``) and leaves absent objects ``None``; with int64 RAM its objects are right, and
its ``detect`` gives them exactly, faster (``games/readers/qbert.py``).
"""

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader, numbered_keys, pop_numbered

INSTRUCTION = (
    "In Q*bert, you control Q*bert hopping on an isometric pyramid of cubes. "
    "Actions: 0=NOOP, 1=FIRE (use flying disk), 2=UP (upper-right), 3=RIGHT (lower-right), 4=LEFT (upper-left), 5=DOWN (lower-left). "
    "All movement is diagonal on the pyramid. "
    "The goal is to change every cube to the destination color by hopping on it (25 pts per cube). "
    "Completing a round (all cubes correct color) earns a 3100-point bonus. "
    "Enemies: Red/Purple Balls bounce down the pyramid - avoid them. "
    "Coily (snake) chases Q*bert - lure him off the edge via flying disks for 500 pts. "
    "Sam reverts cube colors - catch him for 300 pts. Green Ball freezes enemies - touch for 100 pts. "
    "CRITICAL: jumping off the pyramid edge without a flying disk kills Q*bert. "
    "You start with 4 lives. Bonus lives at certain score thresholds. "
    # authors: "...on left edge avoid UP/DOWN; on right edge avoid UP/RIGHT." - wrong for the left edge (measured)
    "Edge awareness: at the top only RIGHT and DOWN are safe; on the left edge LEFT leads off the pyramid, on the "
    "right edge UP does, and from the bottom row RIGHT and DOWN do. "
    "Strategy: systematically hop on cubes to change colors, avoid enemies, use flying disks to escape Coily. "
    "Analyze the trace to understand when Q*bert dies and optimize movement to color more cubes safely."
)
FEEDBACK = {
    # authors: >= 10000 stops training; >= 5000 "Great progress"; 0 < r < 5000 medium; <= 0 low
    "high": 5000,
    "low": 0,
    "target": 10000,
    "messages": {
        "high": "Great progress! You're scoring {score:g} points ({gap:g} below 10000). Keep changing cubes "
                "to the destination color while avoiding enemies.",
        "medium": "You're scoring {score:g} points ({gap:g} below 10000). Hop on cubes to change them to the "
                  "destination color (25 pts each). Avoid enemies - Coily chases you, red/purple balls bounce "
                  "down. Catch Sam (300 pts) and green balls (100 pts) when safe. Do NOT jump off the pyramid "
                  "edge - it costs a life.",
        "low": "Your score is {score:g} points. You must hop on cubes to change their color and score points. "
               "Avoid jumping off the pyramid edges and avoid enemies.",
    },
}
ROLLOUT_STEPS = 100      # authors: --horizon 100 (also run with 1)
EVAL_MAX_STEPS = 4000    # authors: 1 episode x 4,000 steps (ending at the first lost life: see docs/games.md)
EVAL_EPISODES = 1


CUBES = ((68, 34), (56, 62), (84, 62), (44, 91), (68, 91), (96, 91), (32, 120), (56, 120), (84, 120), (108, 120),
         (20, 149), (44, 149), (68, 149), (96, 149), (120, 149), (8, 178), (32, 178), (56, 178), (84, 178),
         (108, 178), (132, 178))
"""Top-left corners of the 21 cubes, row by row (rows of 1..6). Q*bert standing on a cube is at about
(cube_x + 6, cube_y - 17)."""
ENEMY_TYPES = ("Coily", "PurpleBall", "RedBall")
FRIENDLY_TYPES = ("GreenBall", "Sam")
"""Both in OCAtari's slot order (Coily 24, PurpleBall 25, GreenBall 26, Sam 27), the order in which the authors'
loop appends them."""
FRIENDLY_TYPES_V1 = ("Sam", "GreenBall")
"""Observation version 1 listed Sam first."""
GROUPS = (("Enemies", ENEMY_TYPES), ("Friendlies", FRIENDLY_TYPES), ("Disks", ("Disk",)))
"""The observation's lists and the OCAtari categories each gathers, in order (``Disks`` have no ``type``)."""
SCREEN_W, SCREEN_H = 160, 210
_TYPE_ORDER = {category: i for _, types in GROUPS for i, category in enumerate(types)}


def by_type(item: dict) -> int:
    """The order of ``Enemies`` and ``Friendlies``: by type, in :data:`GROUPS`' order."""
    return _TYPE_ORDER[item["type"]]


def _on_screen(box: dict) -> bool:
    return 0 <= box["x"] < SCREEN_W and 0 <= box["y"] < SCREEN_H


def _groups(friendly_types: tuple[str, ...]) -> tuple:
    """:data:`GROUPS` with these friendlies, each category with its first numbered key: ``((key, typed,
    ((category, category0), ...)), ...)``."""
    return tuple((key, key != "Disks", tuple((category, numbered_keys(category)[0]) for category in types))
                 for key, types in (("Enemies", ENEMY_TYPES), ("Friendlies", friendly_types), ("Disks", ("Disk",))))


_GROUPS = {FRIENDLY_TYPES: _groups(FRIENDLY_TYPES), FRIENDLY_TYPES_V1: _groups(FRIENDLY_TYPES_V1)}


def derive(obs: dict, lives: int, friendly_types: tuple[str, ...] = FRIENDLY_TYPES) -> None:
    """The authors' observation, in place: ``Player`` (absent while falling or between lives); ``Enemies``:
    {x, y, w, h, dx, dy, type}, type Coily, PurpleBall or RedBall (in that order); ``Friendlies``: the same for
    GreenBall and Sam (in that order); ``Disks``: the flying disks still available; each list absent when
    empty; objects off the 160x210 screen dropped; ``lives``."""
    player = obs.get("Player")
    if player is not None and not _on_screen(player):
        del obs["Player"]
    groups = _GROUPS.get(friendly_types) or _groups(friendly_types)
    pop = obs.pop
    for key, typed, categories in groups:
        items = []
        for category, first in categories:
            # a category's objects are ``category`` (one slot) or ``category0, category1, ...``
            single = pop(category, None)
            found = [single] if single is not None else []
            if first in obs:
                found += pop_numbered(obs, category)
            for item in found:
                if 0 <= item["x"] < SCREEN_W and 0 <= item["y"] < SCREEN_H:  # _on_screen, written out
                    if typed:
                        item["type"] = category
                    items.append(item)
        if items:
            obs[key] = items
    obs["lives"] = int(lives)


def derive_space(space) -> None:
    """The Gymnasium space of :func:`derive`'s observation, from the generic one (``games.spaces``)."""
    from games.spaces import LIVES, ListOf, OneOf, ints, with_fields

    on_screen = {"x": (0, SCREEN_W - 1), "y": (0, SCREEN_H - 1)}
    space.take("Cube")  # dropped by its hook
    player, _ = space.take("Player")
    space.add("Player", with_fields(player, **on_screen), optional=True)
    for key, types in GROUPS:
        taken = [space.take(category) for category in types]
        item = with_fields(taken[0][0], **on_screen)
        if key != "Disks":
            item = with_fields(item, type=OneOf(types))
        slots = sum(n for _, n in taken)
        space.add(key, ListOf(item, slots, min_length=1, key=None if key == "Disks" else by_type), optional=True)
    space.add("lives", ints(*LIVES))


def derive_v1(obs: dict, lives: int) -> None:
    """Observation version 1: :func:`derive` with Sam before the GreenBall."""
    derive(obs, lives, FRIENDLY_TYPES_V1)

# The authors' published best scores (PAPER.md; mean over trials ± standard error): their follow-up's aggregate
# (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("follow-up", "h1", 560.0, horizon=1, trials=5, stderr=6.12),
    Published("follow-up", "h100", 505.0, horizon=100, trials=5, stderr=98.23),
)

GAME = Game(
    name="qbert",
    env_id="QbertNoFrameskip-v4",
    ocatari_name="Qbert",
    actions=("NOOP", "FIRE", "UP", "RIGHT", "LEFT", "DOWN"),
    lives=4,
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              eval_episodes=EVAL_EPISODES,
              one_life_episodes=True,
              published=PUBLISHED),
    colours={"Player": (181, 83, 40), "Coily": (146, 70, 192), "PurpleBall": (200, 72, 200),
             "RedBall": (228, 60, 60), "GreenBall": (50, 200, 50), "Sam": (100, 230, 100), "Disk": (84, 138, 210)},
    object_hooks={"Cube": None},  # cubes do not enter the observation (the authors skip them)
    detect=fast_reader("qbert"),
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "qbert.py",
    earlier_observations={1: {"derive": derive_v1}},
)
