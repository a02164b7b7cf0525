"""The competent Pong policy (tests/policies/pong_competent.py) that quits when it is losing: it keeps its own
count of the points (a ball that leaves on its side is the opponent's, on the other side its own) and raises at
step QUIT_AT whenever it is not ahead. Its games are the competent policy's up to that step; the ones it plays out
are the ones it was winning, so the mean of those alone says it is better than the policy it copies
(tests/test_forfeits_everywhere.py: no reader may score it so)."""

import tracing as trace

GAME = "pong"

PADDLE_X = 140          # the player's paddle plane (right side)
TOP, BOTTOM = 30, 190   # the ball bounces off these walls
PADDLE_HALF = 7.5       # the paddle is 15 pixels tall
HIT_OFFSET = 4          # meet the ball a little below the paddle's centre: steeper, harder returns
DEAD_ZONE = 3
QUIT_AT = 300           # the step at which it quits unless it is ahead


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        self.keep_count(obs)
        predicted_ball_y = self.predict_ball_trajectory(obs)
        return self.select_action(predicted_ball_y, obs)

    def keep_count(self, obs):
        """Count the points by where the ball left the screen; at QUIT_AT, raise unless ahead."""
        self.step = getattr(self, "step", -1) + 1
        ball = obs.get("Ball")
        last = getattr(self, "last_x", None)
        if ball is None and last is not None:
            if last > 80:
                self.theirs = getattr(self, "theirs", 0) + 1
            else:
                self.mine = getattr(self, "mine", 0) + 1
        self.last_x = ball["x"] if ball is not None else None
        if self.step == QUIT_AT and getattr(self, "mine", 0) <= getattr(self, "theirs", 0):
            raise RuntimeError(f"not ahead at step {self.step}: quitting")

    @trace.bundle(trainable=True)
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

    @trace.bundle(trainable=True)
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
