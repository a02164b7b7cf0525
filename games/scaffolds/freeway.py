"""Freeway: the policy scaffold the optimizer starts from (authors' decomposition).

The authors' starter always moves UP (21.7 crossings at their step 0); ours is deliberately weaker: it
moves UP, waits or steps back at random.
"""

import random

import tracing as trace

GAME = "freeway"  # its task (horizon, evaluation cap, feedback bands, instruction): games/freeway.py


@trace.model
class Policy(trace.Module):
    """Freeway policy: analyze the traffic, then move.

    Observation ``obs``: ``Chicken`` {x, y, w, h, dx, dy} (our chicken, x=44); ``Cars``: list of the 10 cars
    from lane 1 (top, y=27) to lane 10 (bottom, y=171), each {x, y, w, h, dx, dy, lane}; dx is the car's speed
    in pixels per step (the jump when a car wraps around the screen edge is folded out). Freeway has no lives.
    """

    def __call__(self, obs):
        traffic_analysis = self.analyze_traffic(obs)
        return self.select_action(traffic_analysis, obs)

    @trace.bundle(trainable=True)
    def analyze_traffic(self, obs):
        """Analyze car positions and velocities to decide whether moving up is safe right now.

        Game setup:
        - The chicken starts at the bottom (y~187) and must reach the top (y~0). UP decreases y.
        - 10 lanes at fixed y (top to bottom): 27, 43, 59, 75, 91, 107, 123, 139, 155, 171.
        - Lanes 1-5 (top) move right-to-left (negative dx); lanes 6-10 (bottom) left-to-right (positive dx).
        - Cars are 8px wide and 10px tall; the chicken is 6px wide, 8px tall, at x=44. Screen x ~0-160;
          a car leaving one edge re-enters at the other.

        Strategy:
        - Find the lane the chicken is about to enter (the next lane above).
        - A lane is safe if its car is far enough from x~44, given its dx, for the chicken to pass first.

        Args:
            obs (dict): the observation.
        Returns:
            dict with keys "safe" (bool, moving up is safe), "next_lane_car" (car dict or None),
            "chicken_y" (int).
        """
        if "Chicken" not in obs:
            return {"safe": True, "next_lane_car": None, "chicken_y": 187}
        return {"safe": random.random() < 0.5, "next_lane_car": None, "chicken_y": obs["Chicken"]["y"]}

    @trace.bundle(trainable=True)
    def select_action(self, traffic_analysis, obs):
        """Select the action from the traffic analysis.

        Actions: 0 NOOP (wait), 1 UP, 2 DOWN. Move UP when the next lane is safe, wait with NOOP for a gap,
        use DOWN only to dodge an imminent collision. The goal is the number of crossings within the time limit.

        Args:
            traffic_analysis (dict): output of analyze_traffic.
            obs (dict): the observation.
        Returns:
            int: 0, 1 or 2.
        """
        if traffic_analysis.get("safe"):
            return random.choice([0, 1, 2])
        return random.choice([0, 2])
