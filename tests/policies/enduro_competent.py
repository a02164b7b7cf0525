"""Enduro: a hand-written competent policy (same format and observation keys as games/scaffolds/enduro.py).

Always accelerate; steer away from the closest car that is ahead within reach and laterally overlapping.
"""

import tracing as trace

GAME = "enduro"

REACT_Y = 45     # react to cars at most this far ahead (rel_y >= -REACT_Y)
OVERLAP_X = 16   # centre distance below this is a collision course (tuned on RAM-only boxes: 47-75 nearby)
X_MIN, X_MAX = 30, 130  # player centre range considered
ACTION = {"left": 8, "right": 7, "none": 1}


@trace.model
class Policy(trace.Module):

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Steer away from the nearest car on a collision course."""
        player = obs.get("Player")
        if player is None:
            return {"steer_direction": "none", "threat_close": False, "player_x": 77, "player_y": 140}
        steer, threat = "none", False
        pc = player["x"] + player["w"] / 2
        pb = player["y"] + player["h"]
        blocked = []  # centre positions a car ahead (within REACT_Y) makes unsafe
        for car in obs.get("EnemyCars", []):
            ahead = pb - (car["y"] + car["h"])
            if -4 <= ahead <= REACT_Y:
                cc = car["x"] + car["w"] / 2 + car["dx"] * 2
                blocked.append((cc - OVERLAP_X, cc + OVERLAP_X))
        if any(lo < pc < hi for lo, hi in blocked):
            threat = True
            free = [x for x in range(X_MIN, X_MAX + 1, 2) if not any(lo < x < hi for lo, hi in blocked)]
            if free:
                goal = min(free, key=lambda x: abs(x - pc))
                steer = "right" if goal > pc else "left"
        return {"steer_direction": steer, "threat_close": threat, "player_x": player["x"], "player_y": player["y"]}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Accelerate, steering while accelerating when a car is in the way."""
        return ACTION[situation["steer_direction"]]
