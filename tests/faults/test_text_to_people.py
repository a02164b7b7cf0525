"""Text from policy code reaches a person only made safe (viewers/safe_text.py), tested by effect.

A policy file puts every kind of terminal escape into what it leaves behind: its exception (clear screen, window
title, an OSC 8 link, colours that print a fake "all episodes verified OK", a lone carriage return, backspaces,
the 8-bit CSI ``\\x9b``, a DCS string, a terminal reset, bidirectional overrides and isolates), a node's output,
and raw in a string literal of its own source (which ``blame`` prints); the exception also carries HTML and
Markdown (``<script>``, ``<img onerror=...>``, ``javascript:`` links and images). The same text comes back as a
rejected candidate's exception through ``optimize`` with a scripted model.

``codearcade eval``, ``optimize``, ``blame``, ``runs``, ``sql``, ``report`` and ``doctor`` run as real processes
(their output on pipes: no progress bar, so the command line writes no escape of its own either) and no byte a
terminal acts on reaches stdout or stderr: no C0 control but newline, no DEL, no C1 (as a byte or as a
character), no bidirectional control. The report's README.md, rendered by a CommonMark renderer with HTML on,
has no script, no image but the report's own plots, no ``javascript:`` link and no event handler. The store still
holds the original text.
"""

from __future__ import annotations

import html.parser
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import ROOT, json_reply
from viewers.safe_text import markdown_code, markdown_code_block, markdown_text, terminal_json, terminal_text

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")

# Every kind of sequence, written with Python escapes (the exception and the output are built from this at run time).
ESCAPES = (
    "\x1b[2J\x1b[H"                                              # clear the screen, cursor home
    "\x1b]0;pwned title\x07"                                     # window title, ended by BEL
    "\x1b]8;;https://evil.example/\x1b\\click here\x1b]8;;\x1b\\"  # an OSC 8 hyperlink, ended by ST
    "\x1b[1;32mall episodes verified OK\x1b[0m"                  # colours
    "\rOVERWRITTEN"                                              # a lone carriage return
    "abc\x08\x08\x08"                                            # backspaces
    "\x9b31mC1 CSI"                                              # the 8-bit CSI
    "\x1bPqDCS string\x1b\\"                                     # a device control string
    "\x9d8;;https://evil.example/\x9c"                           # an 8-bit OSC, ended by the 8-bit ST
    "\u202eevil reversed\u202c \u2066isolated\u2069"             # bidirectional override, isolate
    "\x1bc"                                                      # reset the terminal
    "\x07\x7f\x00"                                               # bell, DEL, NUL
)
MARKUP = ('<script>alert(1)</script> <img src=x onerror=alert(2)> [click](javascript:alert(3)) '
          '![pic](javascript:alert(4)) <javascript:alert(5)> [ref]: javascript:alert(6) &#60;script&#62;')
# In source, as raw characters inside a string literal (a CR or a NUL cannot be: one ends the line, the other the
# file), and in a comment (a "Trojan Source" bidi override).
RAW_IN_SOURCE = "".join(c for c in ESCAPES if c not in '\r\x00\\"')  # nor a quote or backslash, in a literal

POLICY = textwrap.dedent('''\
    import tracing as trace

    GAME = "pong"
    ESCAPES = {escapes!r}
    MARKUP = {markup!r}

    @trace.model
    class Policy(trace.Module):
        def __call__(self, obs):
            y = self.predict_ball_trajectory(obs)
            return self.select_action(y, obs)

        @trace.bundle(trainable=True)
        def predict_ball_trajectory(self, obs):
            """Returns the escapes as its output."""
            return ESCAPES

        @trace.bundle(trainable=True)
        def select_action(self, predicted_ball_y, obs):
            """Plays NOOP, then raises with markup and every escape in its message."""
            banner = "{raw}"  # {bidi} a comment
            self.calls = getattr(self, "calls", 0) + 1
            if self.calls > 5:
                raise ValueError(MARKUP + " " + ESCAPES + banner)
            return 0
    ''').format(escapes=ESCAPES, markup=MARKUP, raw=RAW_IN_SOURCE, bidi="\u202e\u2066")

CANDIDATE = ('def select_action(self, predicted_ball_y, obs):\n'
             '    """Raises at once: the message becomes the rejection reason, shown in the progress line."""\n'
             f'    raise RuntimeError({ESCAPES!r} + {MARKUP!r})\n')

# What must never reach a terminal: C0 but newline, DEL, C1, the bidirectional controls (as characters: the
# output is decoded strictly as UTF-8 first, so a raw C1 byte fails the decoding).
UNSAFE = re.compile("[\x00-\x09\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def _cli(*args: str, expect: tuple[int, ...] = (0,)) -> str:
    done = subprocess.run([EXE, *args], cwd=ROOT, capture_output=True, timeout=600)
    assert done.returncode in expect, done.stderr.decode(errors="replace")[-3000:]
    for name, data in (("stdout", done.stdout), ("stderr", done.stderr)):
        text = data.decode("utf-8")  # strict: a raw C1 byte (\x9b) is not UTF-8 and fails here
        found = UNSAFE.search(text)
        where = text[max(found.start() - 60, 0):found.end() + 20] if found else ""
        assert found is None, f"{args[0]}: {found.group()!r} reached {name} at {where!r}"
    return done.stdout.decode() + done.stderr.decode()


class _Tags(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def _rendered_tags(markdown: str) -> list[tuple[str, dict[str, str | None]]]:
    """The HTML tags a CommonMark renderer (raw HTML allowed, GitHub's tables on) makes of ``markdown``."""
    from markdown_it import MarkdownIt

    parser = _Tags()
    parser.feed(MarkdownIt("commonmark", {"html": True}).enable("table").render(markdown))
    return parser.tags


def _assert_no_markup(markdown: str, own_images: set[str]) -> None:
    """No raw markup from the policy's text in ``markdown`` (outside fenced code blocks, where it is inert), and
    none in what a renderer makes of it."""
    lowered = re.sub(r"^(`{3,})\w*\n.*?^\1$", "", markdown, flags=re.S | re.M).lower()
    for raw in ("<script", "<img", "javascript:", "onerror="):
        assert raw not in lowered, f"{raw} is in the Markdown"
    for tag, attrs in _rendered_tags(markdown):
        assert tag != "script"
        assert not any(name.startswith("on") for name in attrs), (tag, attrs)
        assert not any((value or "").strip().lower().startswith("javascript:") for value in attrs.values()), attrs
        if tag == "img":
            assert attrs.get("src") in own_images, attrs
        if tag == "a":
            assert False, f"a link was formed: {attrs}"


@pytest.fixture
def evil_policy(tmp_path: Path) -> Path:
    path = tmp_path / "evil.py"
    path.write_text(POLICY, encoding="utf-8")
    return path


def test_terminal_text_removes_every_sequence_and_keeps_the_words():
    shown = terminal_text(MARKUP + ESCAPES)
    assert UNSAFE.search(shown) is None
    for words in ("all episodes verified OK", "click here", "OVERWRITTEN", "evil reversed", "<script>"):
        assert words in shown
    assert "[2J" not in shown and "pwned title" not in shown and "31m" not in shown  # sequences go whole
    assert terminal_text("one\ntwo") == "one\\ntwo"
    assert terminal_text("one\r\ntwo\tthree", multiline=True) == "one\ntwo three"
    assert terminal_text("a lone surrogate \ud800") == "a lone surrogate \ufffd"
    assert terminal_text("plain text, unchanged") == "plain text, unchanged"
    # --json keeps every character: the same value, and nothing raw that a terminal acts on
    encoded = terminal_json(json.dumps({"e": ESCAPES}, ensure_ascii=False))
    assert json.loads(encoded) == {"e": ESCAPES} and UNSAFE.search(encoded) is None


def test_markdown_escapes_and_fences():
    escaped = markdown_text(MARKUP + ESCAPES)
    _assert_no_markup(escaped, set())
    assert UNSAFE.search(escaped) is None
    code = "a = '```'\nb = '````'\n</code><script>"
    block = markdown_code_block(code, "python")
    assert block.startswith("`````python\n") and block.endswith("\n`````")
    assert [tag for tag, _ in _rendered_tags(block)] == ["pre", "code"]  # the whole block stays one code block
    assert [tag for tag, _ in _rendered_tags(markdown_code("a `` b | <img src=x>"))] == ["p", "code"]
    # GitHub renders $...$ as math: a policy's text is never typeset (its $ escaped, as \$ reads as a $)
    assert markdown_text("cost $x^2$ and $$\\color{red}{y}$$") == \
        "cost \\$x^2\\$ and \\$\\$\\\\color\\{red\\}\\{y\\}\\$\\$"


@pytest.mark.slow
def test_no_escape_reaches_the_terminal_and_no_markup_the_report(evil_policy, store, scripted, tmp_path):
    model = scripted([json_reply({"select_action": CANDIDATE})])
    s = ("--store", str(store.path))
    shown = _cli("eval", str(evil_policy), "--trace", "--max-steps", "40", *s, expect=(1,))
    assert "ended with policy_error" in shown and "all episodes verified OK" in shown  # the words, not the codes
    shown = _cli("optimize", str(evil_policy), "--model", model.model, "--api-base", model.api_base,
                 "--iterations", "1", "--eval-max-steps", "40", "--rollout-steps", "30", "--workers", "2", *s)
    assert "update rejected" in shown and "all episodes verified OK" in shown
    eval_run, optimize_run = (r[0] for r in store.query("SELECT run_id FROM runs ORDER BY created_at"))
    with store.write() as con:  # a label and a run error are shown by `runs`, `report` and `sql`
        con.execute("UPDATE runs SET name = ?, error = ? WHERE run_id = ?", ["x" + ESCAPES, MARKUP + ESCAPES, eval_run])
    assert "banner" in _cli("blame", optimize_run, *s)
    assert "pwned" not in _cli("runs", *s)
    for query in ("SELECT exc_message, output FROM nodes WHERE exc_type IS NOT NULL",
                  "SELECT name, error FROM runs", "SELECT reason FROM rejected_candidates"):
        _cli("sql", query, *s)
        _cli("sql", query, "--json", *s)  # every character kept, as \u escapes
    _cli("doctor", *s)
    for run in (eval_run, optimize_run):
        out = tmp_path / f"report-{run}"
        _cli("report", run, "--out", str(out), *s)
        readme = (out / "README.md").read_text(encoding="utf-8")
        assert UNSAFE.search(readme) is None
        _assert_no_markup(readme, {p.name for p in out.glob("*.png")})
    assert "all episodes verified OK" in readme  # the rejection reason is there, as text
    # Rerun's plain-text documents and logs (the prompt, the reply, the feedback, a policy's error) carried the
    # escapes and bidi overrides as they are; its Markdown ones were made safe already
    recordings = []
    for run in (eval_run, optimize_run):
        recordings.append(tmp_path / f"{run}.rrd")
        _cli("view", run, "--save", str(recordings[-1]), *s)
    from tests.test_rerun import dump

    for path, content in dump(*recordings).items():
        text = json.dumps(content, ensure_ascii=False)
        found = UNSAFE.search(text)
        assert found is None, (path, text[max(found.start() - 80, 0):found.end() + 20])

    # the store keeps what the policy wrote (only the display changed)
    assert any(ESCAPES in e for (e,) in store.query("SELECT error FROM episodes WHERE error IS NOT NULL"))
    assert store.query("SELECT count(*) FROM nodes WHERE output = ?", [json.dumps(ESCAPES)])[0][0] > 0
    assert any(MARKUP in r for (r,) in store.query("SELECT reason FROM rejected_candidates"))
    assert any(RAW_IN_SOURCE in t for (t,) in store.query("SELECT text FROM blobs"))


def test_compare_shows_and_writes_stored_text_safely(tmp_path):
    from viewers.compare_report import text_lines, write_report

    evil = MARKUP + ESCAPES
    side = {"action": 1, "action_name": evil, "nodes": {"f": evil}, "obs": {"Ball": {"x": 1, "y": 2}, "k": evil}}
    data = {"mode": "versions", "game": "pong", "diff": f"-    return 0\n+    return 1  # {evil}\n```\n",
            "versions": [{"label": "A", "ref": f"a{evil}.py", "policy_version_id": "v1", "eval_run": "r1"},
                         {"label": "B", "ref": "b.py", "policy_version_id": "v2", "eval_run": "r2"}],
            "episodes": [{"seed": 0, "first_divergent_step": 3,
                          "A": {"return": 1.0, "length": 9, "end_reason": evil},
                          "B": {"return": 2.0, "length": 9, "end_reason": "truncated"},
                          "around": [{"step": 3, "A": side, "B": side}]}]}
    for line in text_lines(data):
        assert UNSAFE.search(line.replace("\n", "")) is None, line
    readme = write_report(data, tmp_path / "cmp").read_text(encoding="utf-8")
    assert UNSAFE.search(readme) is None
    _assert_no_markup(readme, set())


def test_csv_on_a_terminal_is_made_safe_and_into_a_file_is_the_data():
    """``sql --csv`` printed a policy's error as stored: to a terminal, with its escapes (the table mode cleaned
    them). On a terminal each field is made safe now; into a pipe or a file it is still the data, byte for byte,
    read back as one field (a lone carriage return in it was left unquoted, and split the row in two)."""
    import csv
    import io

    from viewers.tables import write_csv

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    rows = [[ESCAPES + MARKUP, 1], [None, "plain"]]
    shown, piped = Terminal(), io.StringIO()
    write_csv(shown, ["error", "n"], rows)
    write_csv(piped, ["error", "n"], rows)
    assert UNSAFE.search(shown.getvalue().replace("\n", "")) is None and "all episodes verified OK" in shown.getvalue()
    assert list(csv.reader(io.StringIO(piped.getvalue(), newline="")))[1][0] == ESCAPES + MARKUP


def test_a_reproduce_command_names_the_same_file_and_shows_nothing_raw(tmp_path):
    """A report's "Reproduce" command was printed in a code block that drops controls, so for a policy file whose
    name held an escape or a bidi override it named another file. Each word is now quoted for bash, a word with a
    character that is not printable as ANSI-C $'...' escapes: bash reads back the very words (random words of every
    kind of character, read back by bash itself), and the line holds nothing a terminal acts on."""
    import random
    import subprocess

    from pipeline.cli.report import _shell_line

    rng = random.Random(7)
    alphabet = ["a", "Z", "0", " ", "'", '"', "\\", "$", "`", "!", "*", "\n", "\t", "\x1b", "\x07", "\x01",
                "\x7f", "\x85", "\x9b", "\u202e", "\u2028", "\ufeff", "é", "日", "\U0001F600", "\U000E0001"]
    cases = [["codearcade", "eval", "".join(rng.choice(alphabet) for _ in range(rng.randint(1, 12))), "--game", "pong"]
             for _ in range(60)]
    cases.append(["codearcade", "eval", "plain.py"])
    # bash's own printf writes the words it read, each ended by a NUL (no word holds one), a file per line
    script = "\n".join(f"printf '%s\\0' {_shell_line(words)} > {i}" for i, words in enumerate(cases))
    assert all(UNSAFE.search(_shell_line(words)) is None for words in cases)
    done = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert [(tmp_path / str(i)).read_bytes().decode().split("\0")[:-1] for i in range(len(cases))] == cases


@pytest.mark.slow
def test_a_library_s_log_of_a_reply_s_field_reaches_the_terminal_made_safe(store, scripted):
    """litellm logs an unknown ``finish_reason`` ("Unmapped finish_reason '...', defaulting to 'stop'") through its
    own handler, quoting the reply's field whole: a model's escape sequences set the window title and cleared the
    screen of `optimize` (stream or not, OpenAI's route or Anthropic's), and 100 KB of it filled the terminal. Its
    handlers now make each record safe and cut it short first (viewers/safe_text.TerminalSafeRecords)."""
    from tests.conftest import COMPETENT_REPLY

    def body(finish_reason: str) -> dict:
        return {"raw": json.dumps({
            "id": "chatcmpl-1", "object": "chat.completion", "created": 0, "model": "scripted",
            "choices": [{"index": 0, "message": {"role": "assistant", "content": COMPETENT_REPLY},
                         "finish_reason": finish_reason}],
            "usage": {"prompt_tokens": 10, "completion_tokens": 10, "total_tokens": 20}})}

    model = scripted([body("evil" + ESCAPES), body("long " + "words, " * 15_000)])
    shown = _cli("optimize", str(ROOT / "games/scaffolds/pong.py"), "--model", model.model, "--api-base",
                 model.api_base, "--iterations", "2", "--eval-episodes", "1", "--eval-max-steps", "30",
                 "--rollout-steps", "20", "--workers", "1", "--repairs", "0", "--audit-episodes", "0",
                 "--store", str(store.path))  # _cli: no byte a terminal acts on in stdout or stderr
    logged = [line for line in shown.splitlines() if "Unmapped finish_reason" in line]
    assert len(logged) == 2 and "evilclick here" in logged[0] and "verified OK" in logged[0], shown[-3000:]
    assert "long words, words" in logged[1] and len(logged[1]) < 2_300, len(logged[1])  # cut short
    assert "characters)" in logged[1], logged[1][-200:]  # and says how long it was


@pytest.mark.slow
def test_a_hostile_recorded_setting_reaches_the_terminal_made_safe_and_cut(store, scripted):
    """A store handed over whose run's recorded feedback bands hold an unknown key ended ``optimize --resume`` with
    ``TypeError: ... unexpected keyword argument '...'``, the key's escapes (window title, cleared screen, 8-bit
    CSI, bell) and all, and a megabyte of key filled the terminal. Python's own printers now make such a report
    safe and cut it short (``viewers/safe_text.make_python_reports_terminal_safe``; the test below), and the run's
    settings are read as untrusted (``FeedbackBands.from_record``): one line naming the key, escaped and cut."""
    from tests.conftest import COMPETENT_REPLY

    model = scripted([COMPETENT_REPLY])
    _cli("optimize", str(ROOT / "games/scaffolds/pong.py"), "--model", model.model, "--api-base", model.api_base,
         "--iterations", "1", "--eval-episodes", "1", "--eval-max-steps", "30", "--rollout-steps", "20",
         "--workers", "1", "--audit-episodes", "0", "--store", str(store.path))
    (run_id, config), = store.query("SELECT run_id, config FROM runs")
    config = json.loads(config)
    config["feedback_bands"]["odd" + ESCAPES + "y" * 1_000_000] = 1  # what the resumed run is built from
    with store.write() as con:
        con.execute("UPDATE runs SET config = ? WHERE run_id = ?", [json.dumps(config), run_id])
    shown = _cli("optimize", "--resume", run_id, "--iterations", "2", "--store", str(store.path), expect=(2,))
    (line,) = [said for said in shown.splitlines() if "codearcade: error" in said]
    assert "recorded settings cannot be read: feedback_bands" in line and "'odd\\x1b[2J" in line, line
    assert "Traceback" not in shown and len(line) < 400 and len(shown) < 2000, shown  # the megabyte cut short


def test_what_python_prints_itself_is_made_safe_in_the_command_s_process():
    """Python's own printers, each given a message with every escape and a megabyte of text, in the command line's
    process (``codearcade games`` with its handler made to warn, fail in a thread, fail in a finalizer and then
    raise): a warning (``warnings.showwarning``), a thread's uncaught error, an ignored one (``__del__``) and the
    command's own uncaught error reach stderr made safe and cut short; Python printed each raw."""
    script = textwrap.dedent('''\
        import json, sys, threading, warnings
        import pipeline.cli
        from pipeline.cli import games

        TEXT = json.loads(sys.argv[1]) + "y" * 1_000_000

        class Finalized:
            def __del__(self):
                raise RuntimeError("in a finalizer " + TEXT)

        def fail(text):
            raise ValueError(text)

        def handler(args):
            warnings.warn("a warning " + TEXT, UserWarning)
            thread = threading.Thread(target=fail, args=("in a thread " + TEXT,))
            thread.start()
            thread.join()
            Finalized()
            raise RuntimeError("uncaught " + TEXT)

        games.run = handler
        sys.argv = ["codearcade", "games"]
        sys.exit(pipeline.cli.main())
        ''')
    done = subprocess.run([sys.executable, "-c", script, json.dumps(ESCAPES)], cwd=ROOT, capture_output=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 1
    err = done.stderr.decode("utf-8")  # strict: a raw C1 byte is not UTF-8
    found = UNSAFE.search(err)
    assert found is None, f"{found.group()!r} reached stderr at {err[max(found.start() - 60, 0):found.end() + 20]!r}"
    for said in ("UserWarning: a warning click here", "Exception in thread", "in a thread click here",
                 "Exception ignored in", "in a finalizer click here", "RuntimeError: uncaught click here"):
        assert said in err, (said, err[-3000:])
    assert len(err) < 4 * 25_000 and err.count("characters)") >= 4, len(err)  # each megabyte cut, and said so


def test_a_batch_run_s_log_gets_python_s_own_reports_made_safe(tmp_path):
    """A batch run's process (``pipeline.jobs.worker``) writes its run's log, read with cat and tail: an error nothing
    caught there was written by Python's hook, its message raw (here a spec whose setting's name holds every escape).
    It is made safe and cut short as in the command line's process."""
    name = "odd" + ESCAPES + "y" * 100_000  # (an argument of a command: under 128 KiB)
    spec = {"store": str(tmp_path / "s.duckdb"), "config": {name: 1}}
    done = subprocess.run([sys.executable, "-m", "pipeline.jobs.worker", json.dumps(spec)], cwd=ROOT,
                          capture_output=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    err = done.stderr.decode("utf-8")  # strict: a raw C1 byte is not UTF-8
    assert done.returncode == 1, err[-3000:]
    found = UNSAFE.search(err)
    assert found is None, f"{found.group()!r} reached stderr at {err[max(found.start() - 60, 0):found.end() + 20]!r}"
    assert "unexpected keyword argument 'oddclick here" in err, err[-3000:]
    assert len(err) < 30_000 and "characters)" in err, len(err)


@pytest.mark.slow
def test_rerun_s_own_log_stays_off_the_terminal(store, tmp_path):
    """Rerun's Rust logger writes to stderr itself, in colour even on a pipe: ``view --connect`` to a URL where no
    viewer listens put its WARN and ERROR lines (``\\x1b[31mERROR\\x1b[0m ... unable to connect``) on stderr, then
    Python's traceback of the same failure. Its log is off unless RUST_LOG asks for it (``viewers/__init__.py``),
    and the failure is one line saying what to do."""
    import socket

    policy = ROOT / "games/scaffolds/pong.py"
    _cli("eval", str(policy), "--max-steps", "10", "--rerun", "off", "--store", str(store.path))
    with socket.socket() as held:  # a port that is ours and where nothing listens: refused at once
        held.bind(("127.0.0.1", 0))
        url = f"rerun+http://127.0.0.1:{held.getsockname()[1]}/proxy"
        env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
        done = subprocess.run([EXE, "view", "last", "--connect", url, "--store", str(store.path)], cwd=ROOT,
                              capture_output=True, timeout=300, env=env)
    err = done.stderr.decode("utf-8")
    assert "\x1b" not in err, err[-3000:]
    assert done.returncode == 2 and err.strip().splitlines() == [
        f"codearcade: error: no Rerun viewer answered at {url}: start one (`rerun`), or give --spawn, --serve-web or "
        "--save instead"], err[-3000:]


def test_a_server_s_failure_is_printed_made_safe_and_cut(capsys):
    """`serve` prints a request's failure with its traceback (``print_failure``): made safe, but whole, so a
    failure quoting a megabyte an agent sent put the megabyte on the person's terminal. It is cut as Python's own
    reports are now (the start and the end, where the error is named)."""
    from viewers.safe_text import print_failure

    try:
        raise ValueError("\x1b]0;owned\x07" + "x" * 1_000_000 + " the end")
    except ValueError:
        print_failure("codearcade serve: a request failed")
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\x07" not in err, err[:200]
    assert len(err) < 30_000 and err.startswith("codearcade serve: a request failed"), len(err)
    assert "ValueError" in err, err[-500:]
