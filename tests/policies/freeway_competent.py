"""Freeway: a hand-written competent policy (same format and observation keys as games/scaffolds/freeway.py).

Look ahead a few steps: move UP unless the chicken's path over the next steps meets a car; then wait, or step
back if waiting is not safe either.
"""

import tracing as trace

GAME = "freeway"

CHICKEN_X0, CHICKEN_X1 = 44, 50   # chicken spans x 44..50
SPEED = 4                         # chicken moves 4 px per step
HORIZON = 3                       # steps of look-ahead
MARGIN = 1                        # px of safety on each side


@trace.model
class Policy(trace.Module):

    def __call__(self, obs):
        traffic_analysis = self.analyze_traffic(obs)
        return self.select_action(traffic_analysis, obs)

    @trace.bundle(trainable=True)
    def analyze_traffic(self, obs):
        """Is each of UP / NOOP / DOWN collision-free for the next HORIZON steps?"""
        chicken = obs.get("Chicken")
        if chicken is None:
            return {"safe": True, "stay_safe": True, "down_safe": True, "chicken_y": 187}
        cy = chicken["y"]
        cars = obs.get("Cars", [])

        def hit(move):
            for t in range(1, HORIZON + 1):
                y0 = cy + move * SPEED * t
                y1 = y0 + 8
                for car in cars:
                    if car["y"] < y1 and car["y"] + car["h"] > y0:
                        cx = car["x"] + car["dx"] * t
                        if cx < CHICKEN_X1 + MARGIN and cx + car["w"] > CHICKEN_X0 - MARGIN:
                            return True
            return False

        return {"safe": not hit(-1), "stay_safe": not hit(0), "down_safe": not hit(1), "chicken_y": cy}

    @trace.bundle(trainable=True)
    def select_action(self, traffic_analysis, obs):
        """UP when safe, else NOOP when safe, else DOWN when safe, else UP (push through)."""
        if traffic_analysis["safe"]:
            return 1
        if traffic_analysis["stay_safe"]:
            return 0
        if traffic_analysis["down_safe"] and traffic_analysis["chicken_y"] < 185:
            return 2
        return 1
