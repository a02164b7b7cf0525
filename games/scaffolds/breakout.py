"""Breakout: the policy scaffold the optimizer starts from.

The starter code is deliberately weak (it follows the ball's current x with no prediction). As in the paper,
the docstring leaves the right wall's position blank: the optimizer has to infer it from the trajectories.
The environment presses FIRE by itself at the start and after every lost life.
"""

import tracing as trace

GAME = "breakout"  # its task (horizon, evaluation cap, feedback bands, instruction): games/breakout.py


@trace.model
class Policy(trace.Module):
    """Breakout policy: predict the ball's landing x, choose where the paddle should be, move there.

    Observation ``obs`` is a dict: ``Player`` (the paddle) and ``Ball`` map to dicts with ``x, y, w, h, dx,
    dy``; the brick rows are lists under ``RB, OB, YB, GB, AB, BB`` (Red, Orange, Yellow, Green, Aqua, Blue,
    top to bottom), one dict per run of adjacent bricks, left to right: a brick is 8 pixels wide, so a run of
    n bricks has ``w = 8 * n`` (a full row is one dict, x 8, w 144). A cleared row is missing, and so is
    ``Ball`` while no ball is in play. ``lives``: lives left (5 at the start).
    """

    def __call__(self, obs):
        pre_ball_x = self.predict_ball_trajectory(obs)
        target_x = self.generate_paddle_target(pre_ball_x, obs)
        return self.select_paddle_action(target_x, obs)

    @trace.bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        """Predict the x where the ball will reach the paddle plane.

        Game facts: the left wall is at x=9, the right wall at x=??? . The paddle plane is y=189. Brick rows
        sit at y = 57, 63, 69, 75, 81, 87 (red to blue). The ball bounces off walls, bricks and the paddle;
        higher bricks make it faster. ``dy > 0`` means the ball is falling toward the paddle.

        Returns:
            float | None: predicted x at y=189, or None when no ball is in play.
        """
        ball = obs.get("Ball")
        if ball is None:
            return None
        return ball["x"]

    @trace.bundle(trainable=True)
    def generate_paddle_target(self, pre_ball_x, obs):
        """Choose the x the paddle's centre should move to.

        Strategy tips: first make sure the ball is returned; then offset the paddle so the ball bounces
        toward gaps and tunnels that lead to the high-value rows (red and orange: 7 points; yellow and green:
        4; aqua and blue: 1). A perfect game scores 864.

        Returns:
            float | None: target x for the paddle's centre, or None to stay put.
        """
        return pre_ball_x

    @trace.bundle(trainable=True)
    def select_paddle_action(self, target_x, obs):
        """Move the paddle toward ``target_x``.

        Actions: 0 NOOP, 2 RIGHT (x increases), 3 LEFT. The paddle is 16 pixels wide; its ``x`` is its left
        edge.

        Returns:
            int: 0, 2 or 3.
        """
        player = obs.get("Player")
        if player is None or target_x is None:
            return 0
        if target_x > player["x"]:
            return 2
        return 3
