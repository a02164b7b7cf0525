"""Space Invaders: the policy scaffold the optimizer starts from.

The starter code is deliberately weak: it shoots at random and never moves.
"""

import random

import tracing as trace

GAME = "space_invaders"  # its task (horizon, evaluation cap, feedback bands, instruction): games/space_invaders.py


@trace.model
class Policy(trace.Module):
    """Space Invaders policy: decide whether to shoot and where to move, then combine both into an action.

    Observation ``obs`` is a dict: ``Player`` (our cannon), ``Shield0..Shield2``, ``Alien0..AlienN`` (numbered
    densely, only living aliens), ``Satellite`` (the mystery ship, when present) and bullets under keys that
    start with ``Bullet``. Each maps to a dict with ``x, y, w, h, dx, dy``. Player bullets move up (negative
    dy), alien bullets down (positive dy); dy is 0 on the step a bullet appears.
    """

    def __call__(self, obs):
        shoot = self.decide_shoot(obs)
        movement = self.decide_movement(obs)
        return self.combine_actions(shoot, movement)

    @trace.bundle(trainable=True)
    def decide_shoot(self, obs):
        """Decide whether to fire this step.

        Game facts: firing has a cooldown and only one player bullet can be on screen at a time, so a shot
        while a bullet is in flight is wasted. Aliens descend over time; lower rows are worth fewer points.

        Returns:
            bool: True to fire.
        """
        return random.random() < 0.5

    @trace.bundle(trainable=True)
    def decide_movement(self, obs):
        """Decide the horizontal movement of the cannon.

        Game facts: the screen is 160 pixels wide. Shields (at y~157) absorb bullets from both sides. Three
        lives; a life is lost when an alien bullet hits the cannon.

        Returns:
            int: -1 move left, 0 stay, 1 move right.
        """
        return 0

    @trace.bundle(trainable=True)
    def combine_actions(self, shoot, movement):
        """Combine the shooting and movement decisions into one Atari action.

        Actions: 0 NOOP, 1 FIRE, 2 RIGHT, 3 LEFT, 4 RIGHT+FIRE, 5 LEFT+FIRE.

        Returns:
            int: an action in 0..5.
        """
        if shoot:
            return 1
        return 0
