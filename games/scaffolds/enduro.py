"""Enduro: the policy scaffold the optimizer starts from (authors' decomposition).

The authors' Enduro starter already accelerates and dodges (it scored 49 at their step 0); ours is
deliberately weaker: it never reacts to cars and steers at random a third of the time.
"""

import random

import tracing as trace

GAME = "enduro"  # its task (horizon, evaluation cap, feedback bands, instruction): games/enduro.py


@trace.model
class Policy(trace.Module):
    """Enduro policy: analyze the cars ahead, then pick a driving action.

    Observation ``obs``: ``Player`` {x, y, w, h, dx, dy}; ``EnemyCars``: list of {x, y, w, h, dx, dy, rel_x,
    rel_y} sorted by proximity (largest y first), absent when no car is visible; ``nearest_enemy_rel_x`` and
    ``nearest_enemy_rel_y`` of the first car (absent with it). Enduro has no lives.
    """

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Analyze the positions of enemy cars relative to the player and decide which way to steer, if any.

        Coordinate system:
        - The screen is ~160px wide. The player's car is near x=77, y=139-144 and moves sideways (x 14-142).
        - Enemy cars approach from ahead (smaller y, from ~56) toward the player (larger y, up to ~150).
        - Both player and enemy cars are 16px wide (boxes); the road curves, shifting all x-positions.

        Scoring:
        - +1 for each car you overtake, -1 for each car that overtakes you.
        - Collisions slow you down dramatically, causing nearby cars to pass you.

        Steering principle: steer away from an enemy that is laterally close (rel_x > 0: enemy to the right,
        steer left; rel_x < 0: steer right). React only to cars close enough to collide.

        Args:
            obs (dict): the observation.
        Returns:
            dict with keys "steer_direction" ("left", "right" or "none"), "threat_close" (bool),
            "player_x", "player_y".
        """
        if "Player" not in obs:
            return {"steer_direction": "none", "threat_close": False, "player_x": 77, "player_y": 140}
        player = obs["Player"]
        return {"steer_direction": "none", "threat_close": False, "player_x": player["x"], "player_y": player["y"]}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Select the driving action from the situation analysis.

        Actions: 0 NOOP (coast, loses speed), 1 FIRE (accelerate), 2 RIGHT, 3 LEFT (steer without
        accelerating), 4 DOWN (brake), 5 DOWNRIGHT, 6 DOWNLEFT (brake + steer), 7 RIGHTFIRE, 8 LEFTFIRE (steer +
        accelerate). Speed is essential for overtaking; actions with FIRE (1, 7, 8) keep it.

        Args:
            situation (dict): output of analyze_situation.
            obs (dict): the observation.
        Returns:
            int: action index 0-8.
        """
        if random.random() < 0.33:
            return random.choice([2, 3])
        return 0
