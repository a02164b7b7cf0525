"""Seaquest: shoot sharks and submarines, rescue divers and surface for air; four lives.

Everything codearcade knows about the game: environment, actions, the authors' task (``seaquest_training.py``
of ameliakuang/LLM-Game-Playing-Agents), the observation and Rerun colours. The policy scaffold is
``games/scaffolds/seaquest.py``.

Observation (the authors' ``trace_envs/seaquest.py`` with full boxes, plus two fields of ours): :func:`derive`
groups the enemies (Shark, Submarine, EnemyMissile, SurfaceSubmarine: OCAtari's slot order, as the authors list
them) into ``Enemies`` and the divers into ``Divers``; the player's torpedo, the oxygen bar and the
collected-diver icons leave the policy's observation (the authors skip them; they stay in the stored steps) but
give ``oxygen`` (the bar's width, OCAtari's ``min(RAM[102], 63)``; 0 when the bar is gone) and
``divers_collected`` (the icons, 0-6). The authors' observation has neither, though their instruction asks the
policy to surface before the oxygen runs out. OCAtari 2.2.1 names the surface patrol ``SurfaceSubmarine`` (the
authors' fork lists no such class, so their filter drops it; ours counts it as an enemy). The direction the sub
faces (RAM[86]) is not an object and is not in the observation. With int64 RAM the extractor is right (uint8
under numpy 2 raises OverflowError).
Its ``detect`` gives OCAtari's objects exactly, faster (``games/readers/seaquest.py``).
"""

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader, numbered_keys, pop_numbered

INSTRUCTION = (
    "In Seaquest, you pilot a submarine rescuing divers and fighting enemies underwater. "
    "Actions: 0=NOOP, 1=FIRE, 2=UP, 3=RIGHT, 4=LEFT, 5=DOWN, "
    "6=UPRIGHT, 7=UPLEFT, 8=DOWNRIGHT, 9=DOWNLEFT, "
    "10=UPFIRE, 11=RIGHTFIRE, 12=LEFTFIRE, 13=DOWNFIRE, "
    "14=UPRIGHTFIRE, 15=UPLEFTFIRE, 16=DOWNRIGHTFIRE, 17=DOWNLEFTFIRE. "
    "Rescue divers by swimming into them (50+ pts each, increases per surface). "
    "Shoot enemies - sharks and enemy subs (20+ pts each, increases per surface). "
    "CRITICAL: oxygen depletes constantly. You MUST surface (move to top of screen) before it runs out or you lose a life. "
    "Collect 6 divers then surface for maximum bonus points (gold ingots). "
    "Colliding with enemies destroys your sub - shoot them from a distance. "
    "You start with 4 submarines. Extra sub every 10,000 pts (max 6 reserves). "
    "Use FIRE combinations (actions 10-17) to shoot while moving - more efficient than stopping to fire. "
    "Strategy: patrol mid-depth to find divers, shoot approaching enemies, surface when oxygen is low or when 6 divers collected. "
    "Analyze the trace to understand when you lose lives (oxygen depletion or enemy collision) and optimize to rescue more divers."
)
FEEDBACK = {
    # authors: >= 5000 stops training; >= 2000 "Great progress"; 0 < r < 2000 medium; <= 0 low
    "high": 2000,
    "low": 0,
    "target": 5000,
    "messages": {
        "high": "Great progress! You're scoring {score:g} points ({gap:g} below 5000). Keep rescuing divers and "
                "shooting enemies. Surface with 6 divers for maximum bonus.",
        "medium": "You're scoring {score:g} points ({gap:g} below 5000). Rescue divers by swimming into them "
                  "(50+ pts each). Shoot enemies with FIRE combinations to clear the path (20+ pts each). "
                  "Surface (move to top) before oxygen runs out - running out of oxygen kills you. Collect 6 "
                  "divers before surfacing for maximum bonus points.",
        "low": "Your score is {score:g} points. You must rescue divers and shoot enemies to score. CRITICAL: "
               "surface before oxygen depletes or you lose a life. Avoid colliding with enemies - shoot them "
               "from a distance.",
    },
}
ROLLOUT_STEPS = 100      # authors: --horizon 100 (also run with 1)
EVAL_MAX_STEPS = 4000    # authors: 1 episode x 4,000 steps (ending at the first lost life: see docs/games.md)
EVAL_EPISODES = 1


SURFACE_Y = 46
"""Player y at the surface; 46..108 in the water."""
ENEMY_LANE_Y = (69, 93, 117, 141)
"""Submarine / Diver y per lane, top to bottom; sharks bob around these."""
ENEMY_TYPES = ("Shark", "Submarine", "EnemyMissile", "SurfaceSubmarine")
"""In OCAtari's slot order (sharks 1-12, submarines 13-24, missiles 29-32, the surface patrol 33), the order in
which the authors' loop appends them: the enemies their list has are at the same positions in ours."""
ENEMY_TYPES_V1 = ("Shark", "Submarine", "SurfaceSubmarine", "EnemyMissile")
"""Observation version 1 put the surface patrol before the missiles."""
OXYGEN_FULL = 63
"""``oxygen`` when the tank is full: OCAtari's oxygen bar is ``min(RAM[102], 63)`` px wide."""
_TYPE_ORDER = {category: i for i, category in enumerate(ENEMY_TYPES)}
MULTI_SLOT = frozenset({"Shark", "Submarine", "Diver", "EnemyMissile", "CollectedDiver"})


def _take(obs: dict, category: str) -> list[dict]:
    if category in MULTI_SLOT:
        return pop_numbered(obs, category) if numbered_keys(category)[0] in obs else []
    item = obs.pop(category, None)
    return [] if item is None else [item]


def by_type(item: dict) -> int:
    """The order of ``Enemies``: by type, in :data:`ENEMY_TYPES`' order."""
    return _TYPE_ORDER[item["type"]]


def _takes(types: tuple[str, ...]) -> tuple[tuple[str, str | None], ...]:
    """Each category with its first numbered key, or None for a one-slot category (what :func:`_take` looks up)."""
    return tuple((category, numbered_keys(category)[0] if category in MULTI_SLOT else None) for category in types)


_ENEMY_TAKES = {ENEMY_TYPES: _takes(ENEMY_TYPES), ENEMY_TYPES_V1: _takes(ENEMY_TYPES_V1)}


def derive(obs: dict, lives: int, enemy_types: tuple[str, ...] = ENEMY_TYPES) -> None:
    """The authors' observation, in place: ``Enemies``: {x, y, w, h, dx, dy, type}, type Shark, Submarine,
    EnemyMissile or SurfaceSubmarine (in that order: :data:`ENEMY_TYPES`); ``Divers``: {x, y, w, h, dx, dy};
    each list absent when empty; ``lives``; ours: ``oxygen`` (0-63, 63 full) and ``divers_collected`` (0-6)."""
    enemies = []
    pop = obs.pop
    for category, first in _ENEMY_TAKES.get(enemy_types) or _takes(enemy_types):  # _take, written out
        if first is None:
            item = pop(category, None)
            if item is not None:
                item["type"] = category
                enemies.append(item)
        elif first in obs:
            for item in pop_numbered(obs, category):
                item["type"] = category
                enemies.append(item)
    if enemies:
        obs["Enemies"] = enemies
    divers = _take(obs, "Diver")
    if divers:
        obs["Divers"] = divers
    pop("PlayerMissile", None)
    bar = pop("OxygenBar", None)
    obs["lives"] = int(lives)
    obs["oxygen"] = 0 if bar is None else bar["w"]
    obs["divers_collected"] = len(_take(obs, "CollectedDiver"))


def derive_space(space) -> None:
    """The Gymnasium space of :func:`derive`'s observation, from the generic one (``games.spaces``)."""
    from games.spaces import LIVES, ListOf, OneOf, ints, with_fields

    taken = [space.take(category) for category in ENEMY_TYPES]
    enemy = with_fields(taken[0][0], type=OneOf(ENEMY_TYPES))
    space.add("Enemies", ListOf(enemy, sum(n for _, n in taken), min_length=1, key=by_type), optional=True)
    diver, slots = space.take("Diver")
    space.add("Divers", ListOf(diver, slots, min_length=1), optional=True)
    space.take("PlayerMissile")
    space.take("OxygenBar")
    _, collected = space.take("CollectedDiver")
    space.add("lives", ints(*LIVES))
    space.add("oxygen", ints(0, OXYGEN_FULL))
    space.add("divers_collected", ints(0, collected))


def derive_v1(obs: dict, lives: int) -> None:
    """Observation version 1: :func:`derive` with the surface patrol before the missiles."""
    derive(obs, lives, ENEMY_TYPES_V1)


# The authors' published best scores (PAPER.md; mean over trials ± standard error): their follow-up's aggregate
# (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("follow-up", "h1", 128.0, horizon=1, trials=5, stderr=22.45),
    Published("follow-up", "h100", 92.0, horizon=100, trials=5, stderr=26.53),
)

GAME = Game(
    name="seaquest",
    env_id="SeaquestNoFrameskip-v4",
    ocatari_name="Seaquest",
    actions=("NOOP", "FIRE", "UP", "RIGHT", "LEFT", "DOWN", "UPRIGHT", "UPLEFT", "DOWNRIGHT", "DOWNLEFT", "UPFIRE",
             "RIGHTFIRE", "LEFTFIRE", "DOWNFIRE", "UPRIGHTFIRE", "UPLEFTFIRE", "DOWNRIGHTFIRE", "DOWNLEFTFIRE"),
    lives=4,
    restorable_reset=True,
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              eval_episodes=EVAL_EPISODES,
              one_life_episodes=True,
              published=PUBLISHED),
    colours={"Player": (187, 187, 53), "Shark": (92, 186, 92), "Submarine": (170, 170, 170),
             "SurfaceSubmarine": (214, 214, 214), "EnemyMissile": (228, 111, 111), "Diver": (66, 72, 200),
             "PlayerMissile": (187, 187, 53), "OxygenBar": (214, 214, 214), "CollectedDiver": (24, 26, 167)},
    detect=fast_reader("seaquest"),
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "seaquest.py",
    earlier_observations={1: {"derive": derive_v1}},
)
