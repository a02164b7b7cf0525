"""The competent Pong policy of pong_competent.py written against Microsoft Trace's policy API, as the authors
write theirs (``import opto.trace as trace``, ``@trace.model``, ``Module``, ``@bundle(trainable=True)``, an
``init`` that nothing calls). Its trainable methods are pong_competent.py's, character for character
(tests/test_trace_api.py checks that, and that the two play the same game with the same nodes)."""

import opto.trace as trace
from opto.trace import bundle, node, Module, GRAPH

GAME = "pong"

PADDLE_X = 140          # the player's paddle plane (right side)
TOP, BOTTOM = 30, 190   # the ball bounces off these walls
PADDLE_HALF = 7.5       # the paddle is 15 pixels tall
HIT_OFFSET = 4          # meet the ball a little below the paddle's centre: steeper, harder returns
DEAD_ZONE = 3


@trace.model
class Policy(Module):
    def init(self):
        pass

    def __call__(self, obs):
        predicted_ball_y = self.predict_ball_trajectory(obs)
        action = self.select_action(predicted_ball_y, obs)
        return action

    @bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        """The y of the ball's centre when it reaches the paddle plane x=140, bouncing off y=30 and y=190.

        Returns None when the ball is not on screen or moves away from the player."""
        ball = obs.get("Ball")
        if ball is None or ball["dx"] <= 0:
            return None
        steps = (PADDLE_X - ball["x"]) / ball["dx"]
        y = ball["y"] + ball["h"] / 2 + ball["dy"] * steps
        span = BOTTOM - TOP
        offset = (y - TOP) % (2 * span)
        return TOP + (offset if offset <= span else 2 * span - offset)

    @bundle(trainable=True)
    def select_action(self, predicted_ball_y, obs):
        """2 moves the paddle up, 3 down, 0 lets it drift. Steer the paddle (where it will be next step,
        given its velocity) to the predicted y, or follow the ball while it moves away."""
        player = obs.get("Player")
        if player is None:
            return 0
        target = predicted_ball_y
        if target is None:
            ball = obs.get("Ball")
            target = ball["y"] + ball["h"] / 2 if ball else (TOP + BOTTOM) / 2
        paddle = player["y"] + PADDLE_HALF + HIT_OFFSET + player["dy"]
        if paddle < target - DEAD_ZONE:
            return 3
        if paddle > target + DEAD_ZONE:
            return 2
        return 0
