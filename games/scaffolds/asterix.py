"""Asterix: the policy scaffold the optimizer starts from (authors' decomposition and starter code).

The starter is deliberately weak: it picks the nearest item and then moves at random.
"""

import random

import tracing as trace

GAME = "asterix"  # its task (horizon, evaluation cap, feedback bands, instruction): games/asterix.py


@trace.model
class Policy(trace.Module):
    """Asterix policy: analyze the lanes, then pick a move.

    Observation ``obs``: ``Player`` {x, y, w, h, dx, dy, lane}; ``Enemies``, ``Consumables``, ``Rewards``:
    lists of {x, y, w, h, dx, dy, type, lane, dist} sorted by Manhattan distance to the player (nearest first),
    each absent when empty; ``enemy_lanes`` and ``safe_collectible_lanes``: lists of lane numbers 0-7;
    ``lives`` (lives left). y grows downward; lane 0 is the top lane.
    """

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Analyze the game state to find the best item to collect and detect nearby dangers.

        Game layout:
        - 8 horizontal lanes at y-positions 26, 42, 58, 74, 90, 106, 122, 138 (16px apart).
        - Objects move horizontally across lanes. Each lane has at most one object.
        - Player can move in 8 directions + NOOP. Screen x range: 0-152.

        Scoring:
        - Collecting a Consumable gives 50+ points; Reward gives bonus points.
        - Touching an Enemy (lyre) costs a life. Losing all lives ends the game (3 lives).
        - An enemy in the same lane is only dangerous if the player is near its x-position; being in the same
          lane but far away horizontally is safe.

        Strategy hints:
        - Use proximity-based danger detection: an enemy is dangerous only if it's within ~30px horizontally.
          Track which lane y-positions are dangerous and which enemies are approaching (<20px).
        - When selecting which item to pursue, factor in: Manhattan distance, item type (Rewards are worth
          more), whether the item's lane is dangerous, and whether the item is in the player's current lane.

        Args:
            obs (dict): the observation (see the class docstring).
        Returns:
            dict with keys "nearest_item" (item dict to pursue, or None), "player_x", "player_y",
            "dangerous_lanes" (list of y-positions with nearby enemies), "approaching_enemies" (list or None).
        """
        if "Player" not in obs:
            return {"nearest_item": None, "player_x": 76, "player_y": 74,
                    "dangerous_lanes": [], "approaching_enemies": None}
        player = obs["Player"]
        items = obs.get("Consumables", []) + obs.get("Rewards", [])
        nearest_item = items[0] if items else None
        return {"nearest_item": nearest_item, "player_x": player["x"], "player_y": player["y"],
                "dangerous_lanes": [], "approaching_enemies": None}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Select an action to move the player toward the chosen item while avoiding enemies.

        Actions: 0 NOOP (stay), 1 UP (smaller y), 2 RIGHT (larger x), 3 LEFT (smaller x), 4 DOWN (larger y),
        5 UPRIGHT, 6 UPLEFT, 7 DOWNRIGHT, 8 DOWNLEFT. Lane y-positions: 26, 42, 58, 74, 90, 106, 122, 138.
        Diagonal actions (5-8) move in two directions at once and are more efficient when the target is in a
        different lane.

        Strategy hints:
        - If an enemy is approaching in the player's lane, evade to an adjacent safe lane (use diagonals to
          also move toward the target).
        - When in the same lane as the target, move horizontally toward it.
        - Be willing to enter a slightly dangerous lane if a high-value Reward is very close.

        Args:
            situation (dict): output of analyze_situation.
            obs (dict): the observation.
        Returns:
            int: action index 0-8.
        """
        if situation is None or situation.get("nearest_item") is None:
            return 0
        return random.choice([1, 2, 3, 4, 5, 6, 7, 8])
