"""Space Invaders: a hand-written competent policy (same interface and trainable methods as
games/scaffolds/space_invaders.py).

Stand under the nearest column of aliens and fire whenever an alien is above the cannon and no shot of ours
is in flight; step aside from an alien bullet that is about to land on the cannon.
"""

import tracing as trace

GAME = "space_invaders"

PLAYER_HALF = 3.5        # the cannon is 7 px wide
ALIEN_HALF = 4           # an alien is 8 px wide
AIM_TOLERANCE = 3        # px between the cannon's and an alien's centres that still counts as "above"
OWN_SHOT_Y = 165         # a bullet that appears below this y (dy 0 on its first step) is ours, just fired
DANGER_Y = 140           # alien bullets below this y are close enough to dodge
DANGER_X = 8             # ... when they are within this many px of the cannon's centre
LEFT_EDGE, RIGHT_EDGE = 38, 117   # the cannon's x range


def _centre(obj, half):
    return obj["x"] + half


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        shoot = self.decide_shoot(obs)
        movement = self.decide_movement(obs)
        return self.combine_actions(shoot, movement)

    @trace.bundle(trainable=True)
    def decide_shoot(self, obs):
        """Fire when an alien's centre is within a few px of the cannon's and none of our shots is in flight
        (ours move up: dy < 0, or dy 0 low on the screen on the step they appear)."""
        player = obs.get("Player")
        if player is None:
            return False
        for key, bullet in obs.items():
            if key.startswith("Bullet") and (bullet["dy"] < 0 or (bullet["dy"] == 0 and bullet["y"] > OWN_SHOT_Y)):
                return False
        cannon = _centre(player, PLAYER_HALF)
        return any(key.startswith("Alien") and abs(_centre(alien, ALIEN_HALF) - cannon) <= AIM_TOLERANCE
                   for key, alien in obs.items())

    @trace.bundle(trainable=True)
    def decide_movement(self, obs):
        """Dodge an alien bullet about to land on the cannon (move to the side away from it); otherwise move
        under the lowest alien (the row that would land first), nearest in x among equals."""
        player = obs.get("Player")
        if player is None:
            return 0
        cannon = _centre(player, PLAYER_HALF)
        for key, bullet in obs.items():
            if key.startswith("Bullet") and bullet["dy"] > 0 and bullet["y"] > DANGER_Y \
                    and abs(bullet["x"] - cannon) < DANGER_X:
                away = 1 if bullet["x"] <= cannon else -1
                if (away < 0 and player["x"] <= LEFT_EDGE) or (away > 0 and player["x"] >= RIGHT_EDGE):
                    away = -away
                return away
        aliens = [alien for key, alien in obs.items() if key.startswith("Alien")]
        if not aliens:
            return 0
        target = min(aliens, key=lambda a: (-a["y"], abs(_centre(a, ALIEN_HALF) - cannon)))
        offset = _centre(target, ALIEN_HALF) - cannon
        if offset > AIM_TOLERANCE:
            return 1
        if offset < -AIM_TOLERANCE:
            return -1
        return 0

    @trace.bundle(trainable=True)
    def combine_actions(self, shoot, movement):
        """0 NOOP, 1 FIRE, 2 RIGHT, 3 LEFT, 4 RIGHT+FIRE, 5 LEFT+FIRE."""
        if movement > 0:
            return 4 if shoot else 2
        if movement < 0:
            return 5 if shoot else 3
        return 1 if shoot else 0
