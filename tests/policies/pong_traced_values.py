"""A Pong policy whose bundled methods take and return every kind of value node capture encodes: the observation,
None, bools, ints, floats (NaN too), numpy scalars, text with non-ASCII characters, tuples, sets, dicts, keyword
and extra positional arguments, a value nested deeper than the bound, a text longer than the bound, and a call
that raises (caught by its caller). ``tests/fixtures/traced_nodes.json.gz`` holds the node rows it left before
node capture was made faster; ``tests/test_tracing.py`` checks that they are stored the same."""

import tracing as trace
import numpy as np

GAME = "pong"


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        ball = self.ball(obs)
        stats = self.stats(obs, ball, scale=1.5)
        label = self.label("bällé ✓ \"quoted\" [x]", stats["n"], 2.5, None, True)
        try:
            self.risky(stats["n"], stats["mean"])
        except ValueError:
            pass
        return self.act(ball, stats, label, obs)

    @trace.bundle(trainable=True)
    def ball(self, obs):
        b = obs.get("Ball")
        return None if b is None else (b["x"], b["y"])

    @trace.bundle(trainable=True)
    def stats(self, obs, ball, scale=1.0):
        ys = [o["y"] for o in obs.values() if isinstance(o, dict)]
        n = len(ys) + (ball[1] if ball else 0)
        value = {"mean": float(np.mean(ys)) * scale, "n": np.int64(n), "nan": float("nan"), "ball": ball,
                 "flags": {n % 2 == 0, True}, "ratio": n / 7, "big": 10 ** 30}
        if n % 5 == 0:
            deep = []
            for _ in range(70):
                deep = [deep]
            value["deep"] = deep
        if n % 11 == 0:
            value["long"] = "é" * 25000
        return value

    @trace.bundle()
    def label(self, text, n, *rest):
        return text * (int(n) % 3)

    @trace.bundle(trainable=True)
    def risky(self, n, mean):
        if n % 3 == 0:
            raise ValueError(f"n is {n}, a multiple of 3 ✗")
        return -mean

    @trace.bundle(trainable=True)
    def act(self, ball, stats, label, obs):
        if ball is None:
            return np.int64(0)
        return 2 if ball[1] < stats["mean"] else 3
