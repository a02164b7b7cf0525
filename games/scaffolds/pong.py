"""Pong: the policy scaffold the optimizer starts from.

The interfaces and docstrings carry the game facts and action meanings; the starter code is deliberately
weak (it moves the paddle at random), as in the paper. Evaluate it with
``codearcade eval games/scaffolds/pong.py`` or improve it with ``codearcade optimize games/scaffolds/pong.py``.
"""

import random

import tracing as trace

GAME = "pong"  # its task (horizon, evaluation cap, feedback bands, instruction): games/pong.py


@trace.model
class Policy(trace.Module):
    """Pong policy: predict where the ball reaches the paddle, then move the paddle there.

    Observation ``obs`` is a dict with keys ``Player`` (our paddle, right), ``Ball`` and ``Enemy`` (left
    paddle); each maps to a dict with ``x, y`` (top-left corner), ``w, h`` (size) and ``dx, dy`` (movement
    since the previous step). A key is missing when the object is not on screen (the ball between points).
    Screen coordinates: y grows downward; the ball bounces at the top wall y=30 and the bottom wall y=190.
    """

    def __call__(self, obs):
        predicted_ball_y = self.predict_ball_trajectory(obs)
        return self.select_action(predicted_ball_y, obs)

    @trace.bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        """Predict the y coordinate where the ball will reach the player's paddle plane.

        Game facts: the player's paddle is at x=140 (right side), the enemy's at x=16 (left side). The ball
        bounces off the top wall at y=30 and the bottom wall at y=190. ``dx > 0`` means the ball moves
        toward the player.

        Args:
            obs (dict): the observation (see the class docstring).
        Returns:
            float | None: the predicted y of the ball at x=140, or None if it cannot be predicted
            (no ball on screen, or the ball moves away from the player).
        """
        ball = obs.get("Ball")
        if ball is None:
            return None
        return ball["y"]

    @trace.bundle(trainable=True)
    def select_action(self, predicted_ball_y, obs):
        """Choose the action that moves the paddle toward the predicted ball position.

        Actions: 0 NOOP (the paddle drifts to a stop), 2 move the paddle up (y decreases), 3 move the paddle
        down (y increases). The paddle is about 15 pixels tall; its ``y`` is its top edge. It accelerates,
        so it keeps moving for a moment after the action changes.

        Args:
            predicted_ball_y (float | None): output of predict_ball_trajectory.
            obs (dict): the observation.
        Returns:
            int: 0, 2 or 3.
        """
        return random.choice([2, 3])
