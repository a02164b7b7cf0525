"""Asterix: collect the items that cross eight lanes and dodge the lyres; three lives.

Everything codearcade knows about the game: environment, actions, the authors' task (instruction, training
horizon, evaluation cap and episodes, staged feedback bands; ``asterix_training.py`` of
ameliakuang/LLM-Game-Playing-Agents), the observation and Rerun colours. The policy scaffold is
``games/scaffolds/asterix.py``.

Observation (the authors' ``trace_envs/asterix.py``, with full boxes and the fields their instruction promises
but their environment never computes): :func:`derive` turns the generic ``Enemy0``, ``Consumable0``,
``Reward0``, ... into the lists ``Enemies``, ``Consumables``, ``Rewards`` (nearest first) and adds ``lane``,
``dist``, ``type``, ``enemy_lanes``, ``safe_collectible_lanes`` and ``lives``. OCAtari's RAM extractor is right
with int64 RAM; its ``detect`` gives its objects exactly, faster (``games/readers/asterix.py``).
"""

from operator import itemgetter

from games.base import SCAFFOLDS, Game, Published, Task, fast_reader, pop_numbered

INSTRUCTION = (
    "In Asterix, you control a player across 8 horizontal lanes (lane 0-7) to collect items and avoid enemies. "
    "Actions: 0=NOOP, 1=UP, 2=RIGHT, 3=LEFT, 4=DOWN, 5=UPRIGHT, 6=UPLEFT, 7=DOWNRIGHT, 8=DOWNLEFT. "
    "Lane y-positions (top to bottom): 26, 42, 58, 74, 90, 106, 122, 138 (16px apart). Screen x: 0-152. "
    "Each lane has at most one object: Consumable (collect for 50-500pts), Reward (collect for bonus pts), "
    "or Enemy/lyre (touching costs a life). "
    "The observation provides 'lane' (0-7) and 'dist' (Manhattan distance) for each object, "
    "'safe_collectible_lanes' (lanes with items but no enemy), and 'enemy_lanes'. "
    "Object lists are sorted by distance (nearest first). "
    "Score by collecting items. Enemies only matter if you're close to their x-position in the same lane. "
    "Diagonal actions (5-8) move in two directions at once."
)
FEEDBACK = {
    # authors: >= 5000 stops training; >= 2000 "Good"; 0 < r < 2000 medium; <= 0 low
    "high": 2000,
    "low": 0,
    "target": 5000,
    "messages": {
        "high": "Good: scoring {score:g} pts on average ({gap:g} below 5000). Consider whether you can collect "
                "items more efficiently or take advantage of lanes you might be avoiding unnecessarily.",
        "medium": "Scoring {score:g} pts on average ({gap:g} below 5000). Points come from collecting "
                  "Consumables and Rewards. Touching an Enemy costs a life. Items in the observation lists "
                  "are sorted by distance (nearest first).",
        "low": "Scoring {score:g} pts on average ({gap:g} below 5000). Points are only earned by collecting "
               "Consumable and Reward items. Move toward items to collect them - compare player x/y with "
               "item x/y to pick the right direction.",
    },
}
ROLLOUT_STEPS = 100      # authors: --horizon 100 (also run with 1)
EVAL_MAX_STEPS = 20000   # authors: 3 episodes x 20,000 steps (each ends at a lost life: see docs/games.md)
EVAL_EPISODES = 3


LANE_Y = (26, 42, 58, 74, 90, 106, 122, 138)
"""y of the 8 lanes, top (lane 0) to bottom (Player, Enemy, Reward; a Consumable sits 1 px lower)."""
PLAYER_HOME = (76, 74)
"""Where distances are measured from while the player is not on screen."""
GROUPS = (("Enemy", "Enemies"), ("Consumable", "Consumables"), ("Reward", "Rewards"))


def _lane(y: int) -> int:
    lane = (y - 18) // 16
    return 0 if lane < 0 else 7 if lane > 7 else lane


def nearest_first(item: dict) -> int:
    """The order of ``Enemies``, ``Consumables`` and ``Rewards``: by ``dist``."""
    return item["dist"]


_BY_DIST = itemgetter("dist")
""":func:`nearest_first` in C: the sort of every step calls it for every item."""
_LANES_OF_MASK = tuple(tuple(lane for lane in range(len(LANE_Y)) if mask >> lane & 1) for mask in range(256))
"""The lanes of each 8-bit lane mask, in order (``derive`` gathers lanes as bits rather than in sets it sorts)."""


def derive(obs: dict, lives: int) -> None:
    """The authors' observation, in place: ``Player`` gains ``lane``; ``Enemies``, ``Consumables``, ``Rewards``
    are lists of {x, y, w, h, dx, dy, type, lane, dist} sorted by Manhattan distance to the player (nearest first,
    ties in OCAtari's slot order), each absent when empty; ``enemy_lanes`` and ``safe_collectible_lanes`` (lanes
    with an item and no enemy) are sorted lane lists, always present; ``lives``."""
    player = obs.get("Player")
    if player is not None:
        px, py = player["x"], player["y"]
        player["lane"] = _lane(py)
    else:
        px, py = PLAYER_HOME
    enemy_mask = item_mask = 0
    for category, key in GROUPS:
        items = pop_numbered(obs, category)
        if not items:
            continue
        mask = 0
        for item in items:
            x, y = item["x"], item["y"]
            lane = (y - 18) // 16  # _lane, written out: it runs for every item of every step
            if lane < 0:
                lane = 0
            elif lane > 7:
                lane = 7
            item["type"] = category
            item["lane"] = lane
            item["dist"] = abs(x - px) + abs(y - py)
            mask |= 1 << lane
        if category == "Enemy":
            enemy_mask |= mask
        else:
            item_mask |= mask
        if len(items) > 1:
            items.sort(key=_BY_DIST)  # stable: ties keep the slot order
        obs[key] = items
    obs["enemy_lanes"] = list(_LANES_OF_MASK[enemy_mask])
    obs["safe_collectible_lanes"] = list(_LANES_OF_MASK[item_mask & ~enemy_mask])
    obs["lives"] = int(lives)


def derive_space(space) -> None:
    """The Gymnasium space of :func:`derive`'s observation, from the generic one (``games.spaces``)."""
    from games.spaces import DISTANCE, LIVES, ListOf, OneOf, ints, with_fields

    lane = ints(0, len(LANE_Y) - 1)
    player, _ = space.take("Player")
    space.add("Player", with_fields(player, lane=lane), optional=True)
    for category, key in GROUPS:
        item, slots = space.take(category)
        item = with_fields(item, type=OneOf([category]), lane=lane, dist=DISTANCE)
        space.add(key, ListOf(item, slots, min_length=1, key=nearest_first), optional=True)
    for key in ("enemy_lanes", "safe_collectible_lanes"):
        space.add(key, ListOf(lane, len(LANE_Y), key=int, strict=True))
    space.add("lives", ints(*LIVES))

# The authors' published best scores (PAPER.md; mean over trials ± standard error): their follow-up's aggregate
# (results/aggregated/all_games_aggregate.csv, the last optimization step)
PUBLISHED = (
    Published("follow-up", "h1", 310.0, horizon=1, trials=5, stderr=65.53),
    Published("follow-up", "h100", 3466.67, horizon=100, trials=5, stderr=2107.68),
)

GAME = Game(
    name="asterix",
    env_id="AsterixNoFrameskip-v4",
    ocatari_name="Asterix",
    actions=("NOOP", "UP", "RIGHT", "LEFT", "DOWN", "UPRIGHT", "UPLEFT", "DOWNRIGHT", "DOWNLEFT"),
    lives=3,
    restorable_reset=True,
    task=Task(instruction=INSTRUCTION, rollout_steps=ROLLOUT_STEPS, eval_max_steps=EVAL_MAX_STEPS, feedback=FEEDBACK,
              eval_episodes=EVAL_EPISODES,
              one_life_episodes=True,
              published=PUBLISHED),
    colours={"Player": (187, 187, 53), "Enemy": (228, 111, 111), "Consumable": (84, 160, 197),
             "Reward": (252, 188, 116)},
    detect=fast_reader("asterix"),
    derive=derive,
    derive_space=derive_space,
    scaffold=SCAFFOLDS / "asterix.py",
)
