"""The in-process sandbox: source checks, restricted builtins, guarded imports, time limits."""

from __future__ import annotations

import time

import pytest

from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import EpisodeTimer, PolicyCodeError, PolicyTimeout, check_source, time_limit

REFUSED = [
    ("import os", "import of 'os'"),
    ("import subprocess", "import of 'subprocess'"),
    ("from socket import socket", "import of 'socket'"),
    ("x = ().__class__", "__class__"),
    ("x = obj.__subclasses__()", "__subclasses__"),
    ("f = eval", "'eval'"),
    ("open('/tmp/x', 'w')", "'open'"),
    ("__import__('os')", "'__import__'"),
    ("g = (i for i in []).gi_frame", "gi_frame"),
    ("try:\n    pass\nexcept:\n    pass", "bare except"),
    ("try:\n    pass\nexcept BaseException:\n    pass", "BaseException"),
    ("from . import x", "relative"),
]


@pytest.mark.parametrize("source, fragment", REFUSED)
def test_check_source_refuses(source, fragment):
    with pytest.raises(PolicyCodeError) as err:
        check_source(source, "<t>")
    assert fragment in str(err.value)


def test_check_source_accepts_ordinary_code():
    check_source(
        "import math, random, collections\nimport numpy as np\nfrom itertools import chain\n"
        "class A:\n    def __init__(self):\n        super().__init__()\n        self._x = [1]\n"
        "try:\n    pass\nexcept (KeyError, ValueError):\n    pass\n"
    )


def _run_policy_body(body: str):
    text = (
        "import tracing as trace\nimport random\nimport numpy as np\n"
        "class Policy(trace.Module):\n    def __call__(self, obs):\n"
        + "".join(f"        {line}\n" for line in body.splitlines())
    )
    return load_policy(text, "p.py").policy({})


@pytest.mark.parametrize(
    "body, error",
    [
        ("return random._os", AttributeError),
        ("return np.load", AttributeError),
        ("return np.ctypeslib", AttributeError),
        ("return getattr(self, '__class__')", AttributeError),
        ("return getattr(random, '_os')", AttributeError),
        ("setattr(random, 'random', None)", AttributeError),
        ("import math\nmath.pi = 3\nreturn 0", AttributeError),
    ],
)
def test_runtime_escapes_fail(body, error):
    with pytest.raises(error):
        _run_policy_body(body)


def test_allowed_modules_work():
    assert _run_policy_body("import math\nreturn int(math.sqrt(16)) + int(np.clip(9, 0, 1))") == 5
    assert _run_policy_body("from collections import deque\nreturn len(deque([1, 2]))") == 2


def test_time_limit_interrupts_a_loop_even_if_it_catches_exception():
    start = time.monotonic()
    with pytest.raises(PolicyTimeout):
        with time_limit(0.2):
            while True:
                try:
                    sum(range(1000))
                except Exception:
                    pass
    assert time.monotonic() - start < 2


def _spin_for(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


@pytest.mark.parametrize("limit", [0.02, 0.1, 0.5])
def test_an_episode_timer_stops_a_call_within_a_tick_of_its_limit_and_again_if_it_is_swallowed(limit):
    timer = EpisodeTimer(limit)
    stops: list[float] = []

    def swallowing(_obs):  # catches the first interruption and goes on
        start = time.monotonic()
        try:
            _spin_for(60)
        except PolicyTimeout:
            stops.append(time.monotonic() - start)
        _spin_for(60)

    with timer:
        start = time.monotonic()
        with pytest.raises(PolicyTimeout, match=f"time limit of {limit:g} s"):
            timer.call(swallowing, None)
        second = time.monotonic() - start
    (first,) = stops
    assert limit <= first < limit + timer.tick + 1.0, (first, timer.tick)  # slack for a busy machine
    assert first < second < first + timer.tick + 1.0, "interrupted again at the next tick"


def test_an_episode_timer_lets_calls_under_its_limit_and_the_waits_between_them_run():
    import os
    import threading

    limit = 0.5  # a tick every 50 ms; each call ~1 ms (far under the limit even on a busy machine), 400 of them
    timer = EpisodeTimer(limit)
    read_end, write_end = os.pipe()
    feeder = threading.Timer(1.5, lambda: os.write(write_end, b"obs"))
    with timer:
        answers = [timer.call(lambda obs: (_spin_for(0.001), obs)[1], step) for step in range(400)]
        feeder.start()
        waited = os.read(read_end, 3)  # a blocking read between calls, three limits long: ~30 ticks interrupt it
        answers.append(timer.call(lambda obs: obs, 400))
    feeder.join()
    os.close(read_end)
    os.close(write_end)
    assert answers == list(range(401)) and waited == b"obs"


def test_an_episode_timer_without_a_limit_sets_no_timer():
    import signal

    before = signal.getsignal(signal.SIGALRM)
    for seconds in (None, 0, float("inf")):
        with EpisodeTimer(seconds) as timer:
            assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
            assert timer.call(lambda obs: obs + 1, 1) == 2
    assert signal.getsignal(signal.SIGALRM) is before


def test_policy_without_policy_class_at_runtime():
    with pytest.raises(PolicyLoadError):
        load_policy("Policy = 3\n", "p.py")
