"""Seaquest: the policy scaffold the optimizer starts from (authors' decomposition and starter code).

The starter is deliberately weak: it moves (and sometimes fires) at random.
"""

import random

import tracing as trace

GAME = "seaquest"  # its task (horizon, evaluation cap, feedback bands, instruction): games/seaquest.py


@trace.model
class Policy(trace.Module):
    """Seaquest policy: analyze the sea, then pick a move (with or without a torpedo).

    Observation ``obs``: ``Player`` {x, y, w, h, dx, dy} (our sub, 16x11; absent while exploding; the way it
    faces, which is the way its torpedoes go, is not in the observation: it turns with LEFT/RIGHT moves);
    ``Enemies``: list of {x, y, w, h, dx, dy, type}, type "Shark", "Submarine", "EnemyMissile" or
    "SurfaceSubmarine" (in that order); ``Divers``: list of {x, y, w, h, dx, dy}; each list absent when empty;
    ``lives`` (lives left); ``oxygen`` (0-63, 63 full, 0 when empty); ``divers_collected`` (0-6, divers on
    board).
    """

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Analyze the submarine's position, nearby enemies, divers and oxygen.

        Game setup:
        - Screen x ~0-160. The sub's y is 46 at the surface and up to 141 at the bottom (y grows downward).
        - Enemies (sharks, subs) and divers move horizontally in 4 lanes: y ~69, 93, 117, 141 (sharks bob a
          few px around them). Colliding with an enemy or an enemy missile destroys your sub.
        - Torpedoes fly horizontally at about the sub's y+7, in the facing direction; one at a time.
        - Rescue divers by touching them; up to 6 carried (divers_collected).
        - Oxygen depletes (a full tank lasts ~400 steps); surface (y=46) to refill. Running out costs a life;
          surfacing with no diver on board also costs a life; surfacing with 6 gives a big bonus.

        Scoring: enemies 20 pts (more after each surfacing), divers 50+ pts, bonus for oxygen left at surfacing.

        Args:
            obs (dict): the observation.
        Returns:
            dict with keys "player_x", "player_y", "nearest_enemy" (dict or None), "nearest_diver" (dict or
            None), "should_surface" (bool).
        """
        if "Player" not in obs:
            return {"player_x": 80, "player_y": 100, "nearest_enemy": None, "nearest_diver": None,
                    "should_surface": False}
        player = obs["Player"]
        return {"player_x": player["x"], "player_y": player["y"], "nearest_enemy": None, "nearest_diver": None,
                "should_surface": False}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Select the action from the situation analysis.

        Actions (18): 0 NOOP, 1 FIRE, 2 UP, 3 RIGHT, 4 LEFT, 5 DOWN, 6 UPRIGHT, 7 UPLEFT, 8 DOWNRIGHT,
        9 DOWNLEFT, 10 UPFIRE, 11 RIGHTFIRE, 12 LEFTFIRE, 13 DOWNFIRE, 14 UPRIGHTFIRE, 15 UPLEFTFIRE,
        16 DOWNRIGHTFIRE, 17 DOWNLEFTFIRE. Moving left/right also turns the sub (and its torpedoes) that way.

        Hints: surface (UP / UPFIRE) when should_surface; move toward a nearby diver; fire while moving
        (10-17) at enemies in your lane; surface with 6 divers for the bonus.

        Args:
            situation (dict): output of analyze_situation.
            obs (dict): the observation.
        Returns:
            int: action index 0-17.
        """
        if situation is None:
            return 1
        return random.choice([2, 3, 4, 5, 11, 12])
