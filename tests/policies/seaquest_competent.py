"""Seaquest: a hand-written competent policy (same format and observation keys as games/scaffolds/seaquest.py).

Sit in an enemy lane and shoot whatever comes along it (turning toward the nearest threat), pick up divers in
reach, and surface when oxygen runs low with at least one diver on board (or with six).
"""

import tracing as trace

GAME = "seaquest"

LANES = (69, 93, 117, 141)   # enemy / diver lane y, top to bottom
LANE_OFFSET = -2             # player y that puts the torpedo (y+7) into a lane
HOME_LANE = 2                # lane to patrol when nothing better
OXY_LOW = 16                 # surface below this oxygen (with >= 1 diver)
CLOSE = 24                   # px: an enemy this close in x blocks entering its lane
SURFACE_Y = 46
ACT = {(0, 0, False): 0, (0, 0, True): 1, (0, -1, False): 2, (1, 0, False): 3, (-1, 0, False): 4,
       (0, 1, False): 5, (1, -1, False): 6, (-1, -1, False): 7, (1, 1, False): 8, (-1, 1, False): 9,
       (0, -1, True): 10, (1, 0, True): 11, (-1, 0, True): 12, (0, 1, True): 13, (1, -1, True): 14,
       (-1, -1, True): 15, (1, 1, True): 16, (-1, 1, True): 17}


def _lane_of(y):
    best = min(range(4), key=lambda i: abs(LANES[i] - y))
    return best if abs(LANES[best] - y) <= 12 else None


@trace.model
class Policy(trace.Module):
    def __init__(self):
        self.facing = "right"  # the observation does not say which way the sub faces: remember our own moves

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Where am I, which lane to hold, what to shoot at, whether to surface."""
        player = obs.get("Player")
        if player is None:  # exploding: the next sub starts facing right
            self.facing = "right"
            return {"player_x": 80, "player_y": 100, "nearest_enemy": None, "nearest_diver": None,
                    "should_surface": False}
        px, py = player["x"] + 8, player["y"]
        my_lane = _lane_of(py - LANE_OFFSET)
        carried = obs.get("divers_collected", 0)
        oxygen = obs.get("oxygen", 63)
        should_surface = carried >= 6 or (oxygen < OXY_LOW and carried >= 1)
        enemies = obs.get("Enemies", [])
        by_lane = {}
        for e in enemies:
            l = _lane_of(e["y"])
            if l is not None:
                by_lane.setdefault(l, []).append(e)
        divers = obs.get("Divers", [])
        diver = min(divers, key=lambda d: abs(d["y"] - py) + abs(d["x"] + 4 - px)) if divers else None
        target_lane = _lane_of(diver["y"]) if diver is not None else HOME_LANE
        in_lane = by_lane.get(my_lane, []) if my_lane is not None else []
        nearest_enemy = min(in_lane, key=lambda e: abs(e["x"] + e["w"] / 2 - px)) if in_lane else None
        return {"player_x": px, "player_y": py, "nearest_enemy": nearest_enemy, "nearest_diver": diver,
                "should_surface": should_surface, "my_lane": my_lane, "target_lane": target_lane,
                "by_lane": by_lane, "facing": self.facing, "oxygen": oxygen}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Surface / refill, else move to the target lane (not into a close enemy) and shoot along the lane."""
        if "my_lane" not in situation:
            return 0
        px, py = situation["player_x"], situation["player_y"]
        if situation["should_surface"] and py <= SURFACE_Y:
            return 0
        if py <= SURFACE_Y + 2 and situation["oxygen"] < 63:
            return 0  # refilling at the surface
        if situation["should_surface"]:
            vy = -1
        else:
            target_y = LANES[situation["target_lane"]] + LANE_OFFSET
            vy = 0 if abs(py - target_y) <= 2 else (1 if target_y > py else -1)
        hx = 0
        if vy:  # do not move into a lane where an enemy is close in x (this step or in 3); sidestep (may be
            # overridden below by the diver / centring / shooting moves)
            for step in (4, 12):
                nxt = _lane_of(py + step * vy - LANE_OFFSET)
                if nxt is None or nxt == situation["my_lane"]:
                    continue
                for e in situation["by_lane"].get(nxt, []):
                    ex = e["x"] + e["w"] / 2
                    if abs(ex - px) < CLOSE + 8 * (step > 4):
                        vy = 0
                        hx = -1 if ex > px else 1
        if situation["should_surface"] and vy:
            return ACT[(hx, vy, situation["nearest_enemy"] is not None)]
        diver = situation["nearest_diver"]
        if diver is not None and situation["my_lane"] is not None and \
                _lane_of(diver["y"]) == situation["my_lane"]:
            hx = 1 if diver["x"] + 4 > px else -1
        elif px < 60:
            hx = 1
        elif px > 100:
            hx = -1
        fire = False
        enemy = situation["nearest_enemy"]
        if enemy is not None:
            ex = enemy["x"] + enemy["w"] / 2
            want = "right" if ex > px else "left"
            fire = True
            if situation["facing"] != want:
                hx = 1 if want == "right" else -1
            elif abs(ex - px) < 30:  # too close: back off while shooting
                hx = -1 if want == "right" else 1
        if hx:
            self.facing = "right" if hx > 0 else "left"
        return ACT[(hx, vy, fire)]
