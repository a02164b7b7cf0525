"""Hostile code, in policy files and proposed by the model: refused or contained, with a recorded reason.

Every case is tried both ways: as the body of ``select_action`` in a policy file evaluated with
``codearcade eval`` (refused at load with a one-line error, or the episode ends with a recorded end reason),
and as a candidate the optimizer validates (rejected with a reason). Afterwards: no file outside the run's
folders was touched, the test process is alive, and the store still holds every earlier row.
"""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.play.validate import CandidateRejected, RuntimeCheck, build_candidate, check_at_runtime, validate_candidate
from tests.conftest import EXAMPLES, pong_policy
from tracing.policy_file import inspect_policy

SENTINEL = Path("/tmp") / f"codearcade-hostile-{uuid.uuid4().hex}"

# (name, body of select_action, expected: "refused" at load | an end reason of the episode)
HOSTILE = [
    ("import os", "import os\nos.system('touch SENTINEL')\nreturn 0", "refused"),
    ("import subprocess", "import subprocess\nsubprocess.run(['touch', 'SENTINEL'])\nreturn 0", "refused"),
    ("import socket", "import socket\nsocket.create_connection(('127.0.0.1', 9))\nreturn 0", "refused"),
    ("open for writing", "open('SENTINEL', 'w').write('x')\nreturn 0", "refused"),
    ("__import__", "__import__('os').system('touch SENTINEL')\nreturn 0", "refused"),
    ("builtins dict", "__builtins__['open']('SENTINEL', 'w')\nreturn 0", "refused"),
    ("subclasses walk", "[c for c in ().__class__.__base__.__subclasses__()]\nreturn 0", "refused"),
    ("function globals", "g = self.select_action.__globals__\nreturn 0", "refused"),
    ("frame walk", "f = (x for x in [1]).gi_frame.f_back\nreturn 0", "refused"),
    ("eval", "return eval('0')", "refused"),
    ("bare except swallowing", "try:\n    pass\nexcept:\n    pass\nreturn 0", "refused"),
    ("getattr dunder", "return getattr(getattr((), '__cl' + 'ass__'), '__ba' + 'se__')", "policy_error"),
    ("private module attribute", "import random\nreturn random._os.system('touch SENTINEL')", "policy_error"),
    ("numpy file writing", "import numpy as np\nnp.save('SENTINEL', np.zeros(3))\nreturn 0", "policy_error"),
    ("ndarray.tofile", "import numpy as np\nnp.zeros(3).tofile('SENTINEL')\nreturn 0", "policy_error"),
    ("while True", "while True:\n    pass", "timeout"),
    ("loop that catches Exception", "while True:\n    try:\n        sum(range(100))\n    except Exception:\n        pass",
     "timeout"),
    ("deep recursion", "def down(n):\n    return down(n + 1)\nreturn down(0)", "policy_error"),
    ("10 GB allocation", "x = bytearray(10 * 2**30)\nreturn 0", "policy_error"),
    ("sys.exit", "raise SystemExit(0)", "policy_error"),
    ("os._exit through a module", "import random\nrandom._os._exit(0)", "policy_error"),
    ("modify a module", "import math\nmath.pi = 3\nreturn 0", "policy_error"),
    ("setattr on a module", "import random\nsetattr(random, 'random', None)\nreturn 0", "policy_error"),
    ("returns NaN", "return float('nan')", "policy_error"),
    ("returns None", "return None", "policy_error"),
    ("returns 7", "return 7", "policy_error"),
    ("returns a string", "return 'up'", "policy_error"),
    ("returns a bool", "return True", "policy_error"),
]


def _body(body: str) -> str:
    return body.replace("SENTINEL", str(SENTINEL))


@pytest.fixture(scope="module")
def healthy_store(tmp_path_factory):
    """A store holding a healthy earlier run, shared by every case (each must leave its rows alone)."""
    from store import Store

    store = Store(tmp_path_factory.mktemp("hostile") / "hostile.duckdb")
    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "60", "--store", str(store.path)]) == 0
    return store


@pytest.mark.parametrize("name, body, expected", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_policy_file(name, body, expected, healthy_store, tmp_path, capsys):
    before = healthy_store.query("SELECT count(*) FROM steps WHERE episode_id IN "
                                 "(SELECT episode_id FROM episodes ORDER BY started_at LIMIT 1)")[0][0]
    path = tmp_path / "hostile.py"
    path.write_text(pong_policy(_body(body)))
    code = main(["eval", str(path), "--call-time-limit", "0.3", "--store", str(healthy_store.path), "--json"])
    out, err = capsys.readouterr()
    if expected == "refused":
        assert code == 2 and len(err.strip().splitlines()) == 1, err
    else:
        assert code == 1, (out, err)
        episode = json.loads(out)["episodes"][0]
        assert episode["end_reason"] == expected, episode
        assert episode["error"], "the reason is recorded"
    assert not SENTINEL.exists(), "nothing outside the run's folders was touched"
    after = healthy_store.query("SELECT count(*) FROM steps WHERE episode_id IN "
                                "(SELECT episode_id FROM episodes ORDER BY started_at LIMIT 1)")[0][0]
    assert after == before == 60, "earlier rows are intact"


OBS = {"Player": {"x": 140, "y": 100, "w": 4, "h": 15, "dx": 0, "dy": 0},
       "Ball": {"x": 100, "y": 50, "w": 2, "h": 4, "dx": 2, "dy": 1}}


def _candidate_source(body: str) -> str:
    return "def select_action(self, predicted_ball_y, obs):\n" + "".join(
        f"    {line}\n" for line in _body(body).splitlines())


@pytest.mark.parametrize("name, body, expected", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_candidate_is_rejected(name, body, expected):
    """Both ways a candidate is checked: static checks and runtime check in one worker (what the optimizer
    does), and each in a worker of its own (where the static checks of the same text passed before)."""
    info = inspect_policy((EXAMPLES / "pong.py").read_text(), "pong.py")
    source = _candidate_source(body)
    check = lambda text: RuntimeCheck(text, "pong", [(0, OBS), (1, OBS)], call_time_limit_s=0.3)  # noqa: E731
    if expected == "refused":
        with pytest.raises(CandidateRejected) as err:
            validate_candidate(info, {"select_action": source}, check)
        assert str(err.value)
    else:
        candidate, reason = validate_candidate(info, {"select_action": source}, check)
        assert candidate is not None and reason, "runs, and its runtime check rejects it"
    with pytest.raises(CandidateRejected) as err:
        candidate = build_candidate(info, {"select_action": source})
        assert candidate is not None
        check_at_runtime(check(candidate.text))
    assert str(err.value)
    assert not SENTINEL.exists()


@pytest.mark.slow
def test_a_candidate_that_kills_its_check_worker_is_not_blamed_on_the_static_checks(monkeypatch):
    """Static and runtime checks share a worker; when it dies (here a C loop the call timer cannot stop, killed
    at the worker's time limit), the static checks run alone to tell which part failed."""
    from pipeline.play import validate

    monkeypatch.setattr(validate, "VET_TIME_LIMIT_S", 2.0)
    info = inspect_policy((EXAMPLES / "pong.py").read_text(), "pong.py")
    source = _candidate_source(f"n = sum(range(10 ** 12))  # {uuid.uuid4().hex}\nreturn 0")
    check = lambda text: RuntimeCheck(text, "pong", [(0, OBS)], call_time_limit_s=0.3,  # noqa: E731
                                      total_time_limit_s=1.0)
    candidate, reason = validate_candidate(info, {"select_action": source}, check)
    assert candidate is not None and reason.startswith("the candidate's check crashed"), reason


def test_a_policy_that_mutates_its_observation_cannot_alter_the_record(store, write_policy, capsys):
    path = write_policy(pong_policy("obs.clear()\nobs['Ball'] = 'gone'\nreturn 0"))
    assert main(["eval", str(path), "--max-steps", "30", "--store", str(store.path)]) == 0
    capsys.readouterr()
    keys = store.query("SELECT DISTINCT o.key FROM (SELECT unnest(objects) AS o FROM steps) ORDER BY 1")
    assert ("Player",) in keys and ("Enemy",) in keys


def test_global_state_does_not_leak_between_episodes(store, write_policy, capsys):
    # a class attribute counter: each episode runs in a fresh process with a freshly loaded policy
    path = write_policy(pong_policy("Policy.calls = getattr(Policy, 'calls', 0) + 1\nreturn 0 if Policy.calls < 40 else 7"))
    code = main(["eval", str(path), "--episodes", "2", "--workers", "1", "--max-steps", "30", "--store",
                 str(store.path), "--json"])
    out, _ = capsys.readouterr()
    assert code == 0
    assert [e["length"] for e in json.loads(out)["episodes"]] == [30, 30]
