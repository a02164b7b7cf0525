"""Breakout: the strategy of the paper's best Breakout policy (353 points in 4,000 steps), written here from its
description and printed code, with the interface of games/scaffolds/breakout.py.

- Prediction: where the falling ball's line reaches the paddle plane (y=189), folded between the walls at
  x=9 and x=152; nothing while the ball rises, or after more than 10 folds.
- Target: while the ball is near the wall (y < 90), the middle of the nearest gap wider than 6 px between
  neighbouring entries of a brick row, when within 30 px of the prediction; otherwise the prediction, 3 px
  against the ball's horizontal direction.
- Action: move the paddle's centre toward the target, with a dead zone that widens while the ball is high
  and fast.

Gaps are measured between the list's neighbouring entries, so the policy sees the same gaps whether a row is
a list of 8-pixel bricks (observation version 1) or of runs of bricks (the authors' Blocks, version 2).
"""

import tracing as trace

GAME = "breakout"

LEFT_WALL = 9
RIGHT_WALL = 152
PADDLE_Y = 189
MAX_FOLDS = 10
ROWS_BOTTOM_UP = ("BB", "AB", "GB", "YB", "OB", "RB")
MIN_GAP = 6           # px between two entries of a row for the ball to pass
NEAR_WALL_Y = 90      # the ball is among (or just under) the bricks above this y
GAP_REACH = 30        # px from the prediction within which a gap is aimed at
RETURN_OFFSET = 3     # px against the ball's horizontal direction: a safe return
BASE_DEAD_ZONE = 3


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        pre_ball_x = self.predict_ball_trajectory(obs)
        target_x = self.generate_paddle_target(pre_ball_x, obs)
        return self.select_paddle_action(target_x, obs)

    @trace.bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        """x where the falling ball reaches y=189, folded between the walls; None while it rises."""
        ball = obs.get("Ball")
        if ball is None or ball["dy"] <= 0:
            return None
        x = ball["x"] + ball["dx"] * ((PADDLE_Y - ball["y"]) / ball["dy"])
        folds = 0
        while x < LEFT_WALL or x > RIGHT_WALL:
            x = 2 * LEFT_WALL - x if x < LEFT_WALL else 2 * RIGHT_WALL - x
            folds += 1
            if folds > MAX_FOLDS:
                return None
        return x

    @trace.bundle(trainable=True)
    def generate_paddle_target(self, pre_ball_x, obs):
        """The nearest wide gap in the wall while the ball is near it, else a safe return."""
        ball = obs.get("Ball")
        if pre_ball_x is None or ball is None:
            return None
        gaps = []
        for row in ROWS_BOTTOM_UP:
            entries = obs.get(row, [])
            for left, right in zip(entries, entries[1:]):
                start, end = left["x"] + left["w"], right["x"]
                if end - start > MIN_GAP:
                    gaps.append((start + end) / 2)
        if ball["y"] < NEAR_WALL_Y and gaps:
            nearest = min(gaps, key=lambda gap: abs(gap - pre_ball_x))
            if abs(nearest - pre_ball_x) < GAP_REACH:
                return nearest
        return pre_ball_x + (-RETURN_OFFSET if ball["dx"] > 0 else RETURN_OFFSET)

    @trace.bundle(trainable=True)
    def select_paddle_action(self, target_x, obs):
        """2 RIGHT / 3 LEFT toward the target, 0 within a dead zone that grows with the ball's height and speed."""
        player = obs.get("Player")
        if target_x is None or player is None:
            return 0
        centre = player["x"] + player["w"] / 2
        ball = obs.get("Ball", {})
        height = (PADDLE_Y - ball.get("y", PADDLE_Y)) / PADDLE_Y
        speed = abs(ball.get("dy", 0)) / 4
        dead_zone = BASE_DEAD_ZONE * (1 + height + speed)
        if abs(centre - target_x) < dead_zone:
            return 0
        return 3 if centre > target_x else 2
