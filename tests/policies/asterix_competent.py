"""Asterix: a hand-written competent policy (same format and observation keys as games/scaffolds/asterix.py).

Pick the best reachable item (value / distance, skipping items whose path crosses an enemy), dodge enemies
in the current and the next lane, and combine the vertical and horizontal moves into one (diagonal) action.
"""

import tracing as trace

GAME = "asterix"

DANGER_X = 26        # an enemy closer than this horizontally (after its move) is a threat
LOOKAHEAD = 3        # steps of enemy motion considered
REWARD_BONUS = 2.0   # Rewards are worth more than Consumables
ACTION = {(0, 0): 0, (0, -1): 1, (1, 0): 2, (-1, 0): 3, (0, 1): 4, (1, -1): 5, (-1, -1): 6, (1, 1): 7, (-1, 1): 8}


@trace.model
class Policy(trace.Module):

    def __call__(self, obs):
        situation = self.analyze_situation(obs)
        return self.select_action(situation, obs)

    @trace.bundle(trainable=True)
    def analyze_situation(self, obs):
        """Threatened lanes (enemy near the player's x soon) and the item to go for."""
        player = obs.get("Player")
        if player is None:
            return {"nearest_item": None, "player_x": 76, "player_y": 74, "dangerous_lanes": [],
                    "approaching_enemies": None}
        px = player["x"] + player["w"] / 2
        lane = player["lane"]
        enemies = obs.get("Enemies", [])
        threat = {}
        for e in enemies:
            ex = e["x"] + e["w"] / 2
            gap = min(abs(ex + e["dx"] * t - px) for t in range(LOOKAHEAD + 1))
            threat[e["lane"]] = min(threat.get(e["lane"], 999), gap)
        dangerous = sorted(l for l, g in threat.items() if g < DANGER_X)
        best, best_score = None, -1.0
        for item in obs.get("Consumables", []) + obs.get("Rewards", []):
            lo, hi = sorted((lane, item["lane"]))
            if any(l in dangerous for l in range(lo, hi + 1) if l != item["lane"]):
                continue
            value = REWARD_BONUS if item["type"] == "Reward" else 1.0
            score = value / (item["dist"] + 10)
            if score > best_score:
                best, best_score = item, score
        return {"nearest_item": best, "player_x": player["x"], "player_y": player["y"],
                "dangerous_lanes": dangerous, "approaching_enemies": None, "lane": lane, "threat": threat}

    @trace.bundle(trainable=True)
    def select_action(self, situation, obs):
        """Dodge first, then move toward the chosen item (diagonals when both axes differ)."""
        if "lane" not in situation:
            return 0
        lane = situation["lane"]
        dangerous = situation["dangerous_lanes"]
        item = situation["nearest_item"]
        vy = hx = 0
        if item is not None:
            if item["lane"] < lane:
                vy = -1
            elif item["lane"] > lane:
                vy = 1
            ix = item["x"] + item["w"] / 2 + item["dx"] * 2
            px = situation["player_x"] + 4
            if ix > px + 3:
                hx = 1
            elif ix < px - 3:
                hx = -1
        if lane in dangerous:  # leave the lane, toward the target if possible
            options = [d for d in ((vy or 1), -(vy or 1)) if 0 <= lane + d <= 7 and lane + d not in dangerous]
            if options:
                vy = options[0]
            else:  # run away horizontally from the closest enemy in the lane
                for e in obs.get("Enemies", []):
                    if e["lane"] == lane:
                        hx = -1 if e["x"] > situation["player_x"] else 1
        elif vy and (lane + vy) in dangerous:
            vy = 0
        return ACTION[(hx, vy)]
