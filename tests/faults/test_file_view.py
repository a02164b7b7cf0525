"""The policy process's narrow file view (``pipeline/boundary/view.py``), asserted by effect.

Before it, every project folder with an ``__init__.py`` was readable from a policy process and the project root
was on its path: ``import tests.policies.pong_competent`` worked (a three-line wrapper around it scored 11.0 in
3,000 steps of Pong, as the competent policy itself), and so did reading the test fixtures' stores and
``examples/``. Each attack here gets past the in-process layer (``typing.sys.modules``) and reports what reached
it by raising it; the test reads the stored episode (or the rejected candidate) and the texts around it. The
view must still hold what a policy imports: every module of the allow-list, numpy's lazily loaded parts, and
the normal episodes of several games play exactly as before.
"""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from pipeline.boundary.view import EMULATOR_PACKAGES
from pipeline.cli import main
from store import Store
from tests.conftest import ROOT, random_policy
from tests.faults.test_boundary import _store_text
from tests.faults.test_outside_attacker import PATHS, _eval, _run

FIXTURE = ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz"
EXAMPLE = ROOT / "examples" / "ablation.toml"


@pytest.fixture
def project_store():
    """A real store in the project's folder (a copy of a fixture's run, as a person's ``codearcade.duckdb``)."""
    path = ROOT / f"codearcade-view-{uuid.uuid4().hex[:12]}.duckdb"
    with gzip.open(FIXTURE, "rb") as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    yield path
    path.unlink(missing_ok=True)


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
def test_the_project_s_tests_examples_and_stores_do_not_reach_a_policy(path, tmp_path, scripted, project_store):
    targets = [FIXTURE, EXAMPLE, ROOT / "tests" / "conftest.py", ROOT / "tests" / "policies" / "pong_competent.py",
               project_store]
    folders = [ROOT, ROOT / "tests", ROOT / "tests" / "fixtures", ROOT / "examples"]
    body = f"""
found = []
for name in ('tests.policies.pong_competent', 'tests.conftest', 'examples'):
    try:
        module = import_module(name)
        found.append('imported ' + name + ' ' + str(module))
    except Exception:
        pass
opened = mods['builtins'].open
for target in {[str(t) for t in targets]!r}:
    try:
        found.append('read ' + opened(target, 'rb').read(64)[::-1].hex())
    except Exception:
        pass
for folder in {[str(f) for f in folders]!r}:
    try:
        found.append('listed ' + ' '.join(os.listdir(folder))[::-1])
    except Exception:
        pass
raise ValueError('view: ' + (' | '.join(found) or 'nothing reached the policy'))
"""
    store, printed, requests = _run(path, tmp_path, scripted, body)
    errors = [e for (e,) in store.query("SELECT error FROM episodes WHERE error IS NOT NULL")]
    reasons = [r for (r,) in store.query("SELECT reason FROM rejected_candidates")] if path == "optimize" else []
    recorded = [text for text in errors + reasons if "view: " in text]
    assert recorded and all("view: nothing reached the policy" in text for text in recorded), recorded
    texts = [printed, _store_text(store.path), json.dumps(requests)]
    for target in targets:
        read = target.read_bytes()[:64][::-1].hex()
        assert not any(read in text for text in texts), f"{target} reached the policy"
    assert not any("pong_competent"[::-1] in text or "ablation.toml"[::-1] in text for text in texts)


def test_a_wrapper_around_a_test_policy_plays_nothing(tmp_path):
    """The issue's wrapper: delegate every step to the competent Pong policy of tests/policies/."""
    body = """
competent = import_module('tests.policies.pong_competent').Policy()
return competent(obs)
"""
    code, summary, printed, store = _eval(tmp_path, body, steps=300)
    episode = summary["episodes"][0]
    assert code == 1 and episode["end_reason"] == "policy_error", episode
    # not there (the minimal filesystem view), or refused (Landlock alone, where the view could not be built)
    assert "No module named 'tests'" in episode["error"] or "PermissionError" in episode["error"], episode["error"]
    assert episode["length"] == 0 and episode["return"] == 0, "not one step was played"


ALL_ALLOWED = """
import math, cmath, random, collections, itertools, functools, operator, statistics, heapq, bisect
import dataclasses, typing, enum, copy, string, re, fractions, decimal, abc
import numpy as np
from opto import trace as opto_trace
"""


def test_every_allowed_module_and_numpy_s_lazy_parts_import_in_a_policy_process(write_policy, tmp_path, capsys):
    """``statistics``, ``fractions``, ``cmath``, ``numpy.fft``, ``numpy.polynomial``, ``numpy.ma`` are not in the
    policy zygote: they are read from the view after the fork (the standard library's folder may be listed)."""
    path = write_policy(random_policy("pong", "VALUE").replace("import random\n", ALL_ALLOWED).replace(
        "return VALUE", "\n        ".join([
            "total = float(np.fft.rfft(np.arange(8.0))[0].real) + np.polynomial.Polynomial([1, 2])(2.0)",
            "total += float(np.ma.masked_array([1, 2], mask=[0, 1]).sum()) + float(np.linalg.det(np.eye(2)))",
            "total += statistics.median([1, 2, 3]) + float(fractions.Fraction(1, 4)) + float(decimal.Decimal('0.25'))",
            "total += cmath.sqrt(-4).imag + heapq.nsmallest(1, [3, 1])[0] + bisect.bisect([1, 2], 1)",
            "return 2 if total == 41.5 else 3"])))
    store = tmp_path / "allowed.duckdb"
    code = main(["eval", str(path), "--max-steps", "3", "--store", str(store), "--json"])
    out, err = capsys.readouterr()
    assert out, err
    episode = json.loads(out)["episodes"][0]
    assert code == 0 and episode["end_reason"] == "truncated" and episode["error"] is None, (episode, err)
    actions = [a for (a,) in Store(store).query("SELECT action FROM steps ORDER BY step")]
    assert actions == [2, 2, 2], "every module imported and computed what it does outside the sandbox"


BEFORE = {"pong": 2.0, "breakout": 154.0, "space_invaders": 1160.0, "asterix": 1100.0}
"""Returns of each game's competent policy (tests/policies/) in 1,500 steps, traced and not, measured with the
previous, wide file view: the narrow one must change nothing of a normal episode."""


@pytest.mark.slow
@pytest.mark.parametrize("game", sorted(BEFORE))
def test_normal_episodes_play_as_before(game, tmp_path, capsys):
    policy = ROOT / "tests" / "policies" / f"{game}_competent.py"
    returns = []
    for trace in ([], ["--trace"]):
        code = main(["eval", str(policy), "--max-steps", "1500", "--store", str(tmp_path / "s.duckdb"), "--json",
                     *trace])
        out, err = capsys.readouterr()
        assert code == 0, err
        (episode,) = json.loads(out)["episodes"]
        assert episode["end_reason"] == "truncated" and episode["error"] is None, episode
        returns.append(episode["return"])
    assert returns == [BEFORE[game]] * 2


VIEW = """
import json, sys
from pipeline.boundary import preload, zygote
role = zygote.ROLES["policy"]
preload.warm(sorted({path.partition(":")[0] for path, _ in role.tasks.values()}), no_emulator=True)
from pipeline.boundary.view import read_paths
print(json.dumps(read_paths()))
"""


def test_the_view_holds_the_project_s_runtime_packages_only():
    """The list itself, as the policy zygote computes it (after its preload): of the project, only the packages a
    policy process runs; the project folder is not listable; no emulator; the standard library without its
    site-packages."""
    done = subprocess.run([sys.executable, "-c", VIEW], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    read, list_only = json.loads(done.stdout)
    venv = Path(sys.prefix).resolve()  # CI's venv is inside the checkout (./.venv): its packages are no project's
    project = sorted(Path(p).relative_to(ROOT).as_posix() for p in read
                     if Path(p).is_relative_to(ROOT) and not Path(p).is_relative_to(venv))
    assert project == ["games", "pipeline", "tracing"], project
    assert str(ROOT) not in list_only
    names = {part.split(".")[0].split("-")[0] for p in read for part in Path(p).parts}
    assert not names & set(EMULATOR_PACKAGES), names & set(EMULATOR_PACKAGES)
    import numpy

    assert str(Path(numpy.__file__).resolve().parent) in read
    assert not any(Path(p).name in ("site-packages", "dist-packages") for p in read + list_only)


def test_a_policy_process_holds_no_descriptor_of_its_file_view(tmp_path):
    """The policy zygote opens the file view's paths once for their Landlock rules (``confine.prepare_workers``),
    and every worker inherits those ~220 descriptors; a worker makes its rules from them and closes them before
    the policy is read. The policy looks at every descriptor it could hold and reports those that name a file or
    a folder (its socket, a pipe or /dev/null are neither)."""
    body = """
stat = import_module('stat')
held = []
for fd in range(4096):
    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        continue
    if stat.S_ISDIR(mode) or stat.S_ISREG(mode):
        held.append(fd)
raise ValueError('held: ' + repr(held) + ' of ' + repr(len(os.listdir('.'))))
"""
    code, summary, printed, store = _eval(tmp_path, body, steps=5)
    errors = [e for (e,) in store.query("SELECT error FROM episodes")]
    assert errors and all("held: [] of " in (e or "") for e in errors), errors
