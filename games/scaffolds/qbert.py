"""Q*bert: the policy scaffold the optimizer starts from (authors' decomposition and starter code).

The starter is deliberately weak: it hops in a random direction every step.
"""

import random

import tracing as trace

GAME = "qbert"  # its task (horizon, evaluation cap, feedback bands, instruction): games/qbert.py


@trace.model
class Policy(trace.Module):
    """Q*bert policy: analyze the pyramid and enemies, then hop.

    Observation ``obs``: ``Player`` {x, y, w, h, dx, dy} (absent while falling or between lives); ``Enemies``:
    list of {x, y, w, h, dx, dy, type} with type "Coily", "PurpleBall" or "RedBall"; ``Friendlies``: the same
    for "GreenBall" and "Sam"; ``Disks``: flying disks still available {x, y, w, h, dx, dy} (left at x=12,
    right at x=140, y=138); each list absent when empty; objects off the 160x210 screen are left out;
    ``lives`` (lives left). Cubes are not in the observation (their corners are fixed: see analyze_situation).
    """

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Analyze Q*bert's position on the pyramid and the enemies to find safe directions.

        Game setup:
        - The pyramid has 6 rows of cubes (1 on top ... 6 at the bottom), 21 cubes. Cube top-left corners:
          row 1 (68,34); row 2 (56,62) (84,62); row 3 x 44,68,96 y 91; row 4 x 32,56,84,108 y 120;
          row 5 x 20,44,68,96,120 y 149; row 6 x 8,32,56,84,108,132 y 178. Q*bert standing on a cube is at
          about (cube_x + 6, cube_y - 17); enemies on a cube are at about the same x.
        - Movement is diagonal: UP = upper-right, LEFT = upper-left, RIGHT = lower-right, DOWN = lower-left.
        - Hopping on a cube changes its color; the round is won when all cubes have the destination color.
        - Jumping off the pyramid kills Q*bert unless a flying disk is there (it carries him to the top).

        Enemies: red/purple balls bounce down the pyramid; Coily (snake, hatched from the purple ball) chases
        Q*bert; Sam reverts cube colors (catch him: 300 pts); the green ball freezes enemies (100 pts).

        Args:
            obs (dict): the observation.
        Returns:
            dict with keys "player_x", "player_y", "nearest_enemy" (dict or None), "nearest_friendly"
            (dict or None), "danger_above" (bool).
        """
        if "Player" not in obs:
            return {"player_x": 80, "player_y": 50, "nearest_enemy": None, "nearest_friendly": None,
                    "danger_above": False}
        player = obs["Player"]
        return {"player_x": player["x"], "player_y": player["y"], "nearest_enemy": None,
                "nearest_friendly": None, "danger_above": False}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Select the hop from the situation analysis.

        Actions: 0 NOOP, 1 FIRE, 2 UP (upper-right), 3 RIGHT (lower-right), 4 LEFT (upper-left),
        5 DOWN (lower-left). A hop takes several steps; input during a hop is ignored.
        Never hop off the pyramid unless a flying disk is there: at the top only RIGHT and DOWN are safe; on
        the left edge LEFT (upper-left) leads off the pyramid, on the right edge UP (upper-right) does, and
        from the bottom row RIGHT and DOWN do. (Measured; the authors' docstring says "left edge: UP and DOWN,
        right edge: UP and RIGHT", which is wrong for the left edge.)

        Args:
            situation (dict): output of analyze_situation.
            obs (dict): the observation.
        Returns:
            int: action index 0-5.
        """
        if situation is None:
            return 0
        return random.choice([2, 3, 4, 5])
