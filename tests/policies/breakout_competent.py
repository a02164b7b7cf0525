"""Breakout: a hand-written competent policy (same interface and trainable methods as games/scaffolds/breakout.py).

Predict where the falling ball reaches the paddle plane, folding its path at the side walls, and bring the
paddle's centre there early, allowing for the paddle's own momentum. While the ball rises, follow it so the
paddle is never far from where it will come down.
"""

import tracing as trace

GAME = "breakout"

LEFT_WALL = 8            # the ball's x never goes below this
RIGHT_WALL = 150         # ... nor above this (the ball is 2 px wide; the right wall's inner edge is x=152)
PADDLE_Y = 189           # the paddle plane
PADDLE_WIDTH = 16
SCREEN_CENTRE = 80
DEAD_ZONE = 7            # px from the target within which the paddle is left to drift (it moves ~22 px a step)
COAST = 0.3              # part of its last move the paddle still makes after the key is released


def _fold(x, low, high):
    """``x`` reflected into [low, high], as a ball bouncing between two walls ends up there."""
    span = high - low
    offset = (x - low) % (2 * span)
    return low + (offset if offset <= span else 2 * span - offset)


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        pre_ball_x = self.predict_ball_trajectory(obs)
        target_x = self.generate_paddle_target(pre_ball_x, obs)
        return self.select_paddle_action(target_x, obs)

    @trace.bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        """The x of the ball's centre when it reaches y=189, bouncing off x=8 and x=150; while it rises, its
        current x; None when no ball is in play."""
        ball = obs.get("Ball")
        if ball is None:
            return None
        if ball["dy"] <= 0:
            return ball["x"] + ball["w"] / 2
        steps = (PADDLE_Y - (ball["y"] + ball["h"])) / ball["dy"]
        return _fold(ball["x"] + ball["dx"] * max(steps, 0), LEFT_WALL, RIGHT_WALL) + ball["w"] / 2

    @trace.bundle(trainable=True)
    def generate_paddle_target(self, pre_ball_x, obs):
        """Where the paddle's centre should be: under the predicted ball, or mid-screen with no ball."""
        if pre_ball_x is None:
            return SCREEN_CENTRE
        return pre_ball_x

    @trace.bundle(trainable=True)
    def select_paddle_action(self, target_x, obs):
        """2 moves right, 3 left, 0 lets the paddle drift. The paddle accelerates and coasts, so steer where
        it is heading (its centre plus part of its last move) toward the target, within a dead zone."""
        player = obs.get("Player")
        if player is None or target_x is None:
            return 0
        paddle = player["x"] + PADDLE_WIDTH / 2 + COAST * player["dx"]
        if paddle < target_x - DEAD_ZONE:
            return 2
        if paddle > target_x + DEAD_ZONE:
            return 3
        return 0
