"""How many files a policy process can list and read: the size of its filesystem view, measured from inside.

A policy file that gets past the in-process layer (``typing.sys.modules['os']``, as ``tests/faults/`` do) walks
the policy process's filesystem from ``/``, from the usual system folders and from every ``sys.path`` entry and
the folders above them (Landlock may let a folder be listed while its parent cannot be; ``/proc`` and ``/sys`` left
out), and tries ``os.open(O_RDONLY)``
on every file it lists; it reports the counts, the readable files per directory (the largest groups) and whether
the project's tests, examples, fixtures and a store beside them could be read, by raising them as its error. It is
played by ``codearcade eval`` as a command, as a user runs it: the real zygote, the real confinement.

    .venv/bin/python bench/file_view.py [--top 12] [--limit N]

``--limit`` stops the walk after N files (a quick run); the figures in docs/sandbox.md are of a whole walk.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

WALKER = '''
import typing
import tracing as trace

GAME = "pong"

@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        return self.act(obs)

    @trace.bundle(trainable=True)
    def act(self, obs):
        mods = typing.sys.modules
        os = mods["os"]
        listed, readable, groups = 0, 0, {}
        starts = ["/", "/usr", "/usr/lib", "/usr/local", "/usr/share", "/lib", "/lib64", "/etc", "/opt", "/srv",
                  "/var", "/tmp", "/root", "/home", "/work", "/dev"] + list(mods["sys"].path)
        for module in list(mods.values()):  # a folder that cannot be listed may hold one that can: those in use
            where = mods["builtins"].getattr(module, "__file__", None)
            if isinstance(where, str):
                starts.append(os.path.dirname(where))
        seen, todo = set(), []
        for start in starts:
            while start and start not in ("/", "."):  # every folder on the way: Landlock may list one, not another
                todo.append(start)
                start = os.path.dirname(start)
        todo.append("/")
        while todo and listed < LIMIT:
            top = todo.pop()
            real = os.path.realpath(top)  # Debian's /lib is /usr/lib: each folder is counted once
            if real in seen or real in ("/proc", "/sys"):
                continue
            seen.add(real)
            try:
                entries = list(os.scandir(top))
            except OSError:
                continue
            for entry in entries:
                if entry.is_dir(follow_symlinks=False):
                    todo.append(entry.path)
                    continue
                listed += 1
                try:
                    fd = os.open(entry.path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
                except OSError:
                    continue
                os.close(fd)
                readable += 1
                group = "/".join(entry.path.split("/")[:DEPTH])
                groups[group] = groups.get(group, 0) + 1
        probes = []
        for path in PROBES:
            try:
                fd = os.open(path, os.O_RDONLY)
                probes.append("read")
                os.close(fd)
            except OSError as exc:
                probes.append(type(exc).__name__)
        top_groups = sorted(groups.items(), key=lambda kv: -kv[1])[:TOP]
        raise ValueError("FILEVIEW " + mods["json"].dumps(dict(listed=listed, readable=readable, groups=top_groups,
                                                                 probes=probes)))
'''


def measure(top: int, limit: int, depth: int) -> dict:
    """Play the walker once with ``codearcade eval``; its report (a dict)."""
    work = Path(tempfile.mkdtemp(prefix="codearcade-fileview-"))
    store = work / "codearcade.duckdb"
    probes = [str(ROOT / "tests" / "policies" / "pong_competent.py"),
              str(ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz"), str(ROOT / "examples" / "ablation.toml"),
              str(ROOT / "tests" / "conftest.py"), str(store)]
    policy = work / "walker.py"
    policy.write_text(WALKER.replace("LIMIT", str(limit)).replace("DEPTH", str(depth)).replace("TOP", str(top))
                      .replace("PROBES", repr(probes)))
    subprocess.run([sys.executable, "-m", "pipeline.cli", "eval", str(ROOT / "games" / "scaffolds" / "pong.py"),
                    "--max-steps", "1", "--store", str(store)], cwd=ROOT, capture_output=True, check=True)
    done = subprocess.run([sys.executable, "-m", "pipeline.cli", "eval", str(policy), "--max-steps", "1",
                           "--call-time-limit", "600", "--episode-time-limit", "900", "--store", str(store), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=1200)
    error = json.loads(done.stdout)["episodes"][0]["error"] or ""
    if "FILEVIEW " not in error:
        raise SystemExit(f"the walker did not report: {error[:2000]}\n{done.stderr[-2000:]}")
    text = error.split("FILEVIEW ", 1)[1]
    report = json.loads(text[:text.rindex("}") + 1])
    report["probe_paths"] = probes
    return report


GRANTED = """
import json, os, sys
from pipeline.boundary import preload, zygote
role = zygote.ROLES["policy"]
preload.warm(sorted({path.partition(":")[0] for path, _ in role.tasks.values()}), no_emulator=True)
from pipeline.boundary.view import read_paths
seen, files = set(), 0
for path in read_paths()[0]:
    if not os.path.isdir(path):
        files += os.path.realpath(path) not in seen
        seen.add(os.path.realpath(path))
        continue
    for top, dirs, names in os.walk(path):
        if os.path.realpath(top) in seen:
            dirs[:] = []
            continue
        seen.add(os.path.realpath(top))
        files += len(names)
print(files)
"""


def granted() -> int:
    """Files below the paths the policy process's Landlock rules let it read (``view.read_paths``, computed as
    the policy zygote computes it: after its preload), counted from outside: what a policy could read if it guessed
    every name (the walk inside finds only what it can list)."""
    done = subprocess.run([sys.executable, "-c", GRANTED], cwd=ROOT, capture_output=True, text=True, check=True)
    return int(done.stdout.split()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--top", type=int, default=12, help="directories shown, most readable files first")
    parser.add_argument("--depth", type=int, default=5, help="path components that name a directory group")
    parser.add_argument("--limit", type=int, default=10**9, help="stop the walk after this many files")
    args = parser.parse_args()
    report = measure(args.top, args.limit, args.depth)
    print(f"files listed: {report['listed']:,}   readable (os.open O_RDONLY): {report['readable']:,}   "
          f"below the read rules: {granted():,}")
    for group, count in report["groups"]:
        print(f"  {count:>8,}  {group}")
    for path, outcome in zip(report["probe_paths"], report["probes"]):
        print(f"  {outcome:<18} {Path(path).relative_to(ROOT) if path.startswith(str(ROOT)) else path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
