"""Untrusted text made safe for where a person sees it: a terminal, a Markdown file, a Markdown document in Rerun.

Text that came from policy code, an LLM's reply or the store (an episode's error, a node's exception, a rejected
candidate's reason, a label, a stored cell, a line of a policy) may hold anything. The store keeps it as it came
(scrubbed of secrets, ``pipeline/boundary/untrusted.py``); only its display is made safe, here, at the edge:

- :func:`terminal_text` for every line the command line prints: escape sequences (CSI ``ESC [ ... m`` colours and
  ``ESC [ 2J`` clearing the screen, OSC ``ESC ] 0;title BEL`` window titles and ``ESC ] 8 ;; url ST`` links, DCS,
  SOS, PM, APC strings, and their 8-bit C1 forms such as ``\\x9b``) are removed whole; every other C0 and C1
  control character (lone carriage returns and backspaces that overwrite what was printed, bells, ``DEL``) is
  removed, a tab becomes a space; bidirectional overrides and isolates (U+202A-U+202E, U+2066-U+2069, U+200E,
  U+200F, U+061C), which reorder what a reader sees, are removed; lone surrogates (which would stop ``print``)
  become U+FFFD. A newline is kept only in a block meant to span lines (``multiline=True``: a diff, a prompt);
  elsewhere it shows as ``\\n``, so one untrusted line can never look like two lines of codearcade's own.
- :func:`markdown_text` for untrusted text inline in a rendered Markdown file (a table cell, a line of a
  report): the same, then ``< > &`` HTML-escaped (no ``<script>``, ``<img onerror=...>`` or entity is formed)
  and the ASCII punctuation Markdown builds links, images, code, emphasis and tables from backslash-escaped
  (``[ ] ( ) { } | ! # * _ ~``, the backtick and the backslash: no ``[text](javascript:...)`` link,
  ``![](...)`` image or ``<javascript:...>`` autolink can form, and a ``|`` cannot end a table cell), and so
  is a colon or equals sign glued to a word (``javascript\\:``, ``onerror\\=``); a renderer shows the text
  as it was.
- :func:`markdown_code` and :func:`markdown_code_block` for code and other literal text (a policy file, a diff, a
  path): a code span or fenced block whose fence is longer than any run of backticks inside, so the text can
  never close it and continue as Markdown.
- :func:`plot_text` for untrusted text in a plot's title or legend: terminal-safe (a font has no glyph for a
  control character, and matplotlib's warning about it would print the character raw on stderr) and with ``$``
  escaped (no mathtext: ``$\\foo$`` would stop the drawing with an error).
- :class:`TerminalSafeRecords` for what a library logs (:func:`make_logs_terminal_safe`): litellm's log quotes a
  reply's fields; every record its handlers write is made safe and cut short first.
- :func:`make_python_reports_terminal_safe` for what Python prints by itself: an uncaught exception's traceback, an
  ignored one's, a warning; made safe and cut short.
- :class:`Markdown`: text a viewer composed itself as Markdown (``**bold**``, a code span it built), passed
  through :func:`markdown_cell` (a table's cell) unescaped.

``--json`` output keeps every character of the value: JSON writes C0 controls (ESC included) as ``\\u``
escapes, and :func:`terminal_json` writes the few it leaves raw (``DEL``, C1, the bidirectional controls, line
separators, lone surrogates) as ``\\u`` escapes too: the same JSON value, with no byte a terminal acts on.
"""

from __future__ import annotations

import html
import logging
import re
import sys

# ECMA-48 escape sequences, 7-bit (ESC ...) and 8-bit (C1): removed whole, so no fragment ("[2J") is left over.
_ESCAPE_SEQUENCE = re.compile(
    r"(?:\x1b\[|\x9b)[\x30-\x3f]*[\x20-\x2f]*[\x40-\x7e]?"  # CSI: parameters, intermediates, final byte
    # OSC, DCS, SOS, PM, APC: a string up to BEL or ST (ESC \ or \x9c); an unterminated one up to the line's end
    r"|(?:\x1b[\]PX^_]|[\x90\x98\x9d\x9e\x9f])[^\x07\x1b\x9c\n]*(?:\x07|\x1b\\|\x9c)?"
    r"|\x1b[\x20-\x2f]*[\x30-\x7e]?"  # any other escape (ESC c resets the terminal, ESC 7 saves the cursor)
)
_BIDI = "\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069"
_UNSAFE = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f" + _BIDI + "\u2028\u2029\ud800-\udfff]")
_DROPPED: dict[int, str | None] = {c: None for c in [*range(0x00, 0x09), *range(0x0b, 0x20), *range(0x7f, 0xa0)]}
_DROPPED.update({ord(c): None for c in _BIDI})
_DROPPED.update({c: "\ufffd" for c in range(0xd800, 0xe000)})
_DROPPED[0x09] = " "


_JSON_RAW = re.compile("[\x7f-\x9f" + _BIDI + "\u2028\u2029\ud800-\udfff]")


def terminal_json(text: str) -> str:
    """A JSON text with the characters JSON leaves raw in strings, but a terminal acts on, written as ``\\u``
    escapes (they occur only inside strings, where the escape means the same character)."""
    return _JSON_RAW.sub(lambda m: f"\\u{ord(m.group()):04x}", text)


def terminal_text(text: object, multiline: bool = False) -> str:
    """``text`` as it may be printed on a terminal (see the module docstring); ``multiline``: a block whose
    newlines are kept."""
    text = text if isinstance(text, str) else str(text)
    if _UNSAFE.search(text) is None and "\t" not in text and (multiline or "\n" not in text):
        return text  # the usual case: nothing to do
    text = _ESCAPE_SEQUENCE.sub("", text)
    text = text.replace("\r\n", "\n").replace("\u2028", "\n").replace("\u2029", "\n").translate(_DROPPED)
    return text if multiline else text.replace("\n", "\\n")


LOG_MESSAGE_CHARS = 2_000
"""Characters of a library's log message shown (:class:`TerminalSafeRecords`): litellm's quotes a reply's field
whole, however long."""


class TerminalSafeRecords(logging.Filter):
    """Makes each log record a handler writes safe for the terminal first: its message formatted, made safe
    (:func:`terminal_text`) and cut to :data:`LOG_MESSAGE_CHARS`, its traceback and stack made safe. A library's own
    log quotes what a server sent it: litellm's "Unmapped finish_reason '...', defaulting to 'stop'" put a reply's
    escape sequences (a window title, a cleared screen) raw on the terminal of every verb that calls a model."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if len(message) > LOG_MESSAGE_CHARS:
            message = f"{message[:LOG_MESSAGE_CHARS]}... ({len(message):,} characters)"
        record.msg, record.args = terminal_text(message), None
        if record.exc_info and not record.exc_text:
            import traceback

            record.exc_text = terminal_text("".join(traceback.format_exception(*record.exc_info)).rstrip("\n"),
                                            multiline=True)
        if record.stack_info:
            record.stack_info = terminal_text(record.stack_info, multiline=True)
        return True


def make_logs_terminal_safe(*loggers: str) -> None:
    """Add :class:`TerminalSafeRecords` to every handler of the named loggers, and to the handler Python writes a
    record with when no logger has one (``logging.lastResort``); once each."""
    handlers = [h for name in loggers for h in logging.getLogger(name).handlers] + [logging.lastResort]
    for handler in handlers:
        if handler is not None and not any(isinstance(f, TerminalSafeRecords) for f in handler.filters):
            handler.addFilter(TerminalSafeRecords())


PYTHON_REPORT_CHARS = 20_000
"""Characters of a traceback or warning Python prints itself (:func:`make_python_reports_terminal_safe`) kept: the
first and last halves, each line cut to :data:`LOG_MESSAGE_CHARS`."""


def _cut_report(text: str) -> str:
    """``text`` (a traceback, a warning) with each line cut to :data:`LOG_MESSAGE_CHARS` and the whole to about
    :data:`PYTHON_REPORT_CHARS`, keeping its start and its end (a traceback's last line names the error)."""
    lines = [line if len(line) <= LOG_MESSAGE_CHARS else f"{line[:LOG_MESSAGE_CHARS]}... ({len(line):,} characters)"
             for line in text.split("\n")]
    text = "\n".join(lines)
    if len(text) > PYTHON_REPORT_CHARS:
        half = PYTHON_REPORT_CHARS // 2
        text = f"{text[:half]}\n... ({len(text) - 2 * half:,} characters left out) ...\n{text[-half:]}"
    return text


def _write_report(text: str, file: object = None) -> None:
    """``text`` (what Python would have printed) cut short and made safe, on ``file`` or stderr; a stream that is
    gone or closed takes nothing, as with Python's own hooks."""
    stream = file if file is not None else sys.stderr
    if stream is None:  # pythonw, a daemon: Python's hooks print nothing either
        return
    try:
        stream.write(terminal_text(_cut_report(text.rstrip("\n")), multiline=True) + "\n")
        stream.flush()
    except (OSError, ValueError):  # a closed or full stream: nothing more can be said
        pass


def _format_exception(exc_type: type[BaseException], exc: BaseException | None, tb: object) -> str:
    import traceback

    return "".join(traceback.format_exception(exc_type, exc, tb))


def _excepthook(exc_type: type[BaseException], exc: BaseException, tb: object) -> None:
    _write_report(_format_exception(exc_type, exc, tb))


def _thread_excepthook(args: object) -> None:
    if args.exc_type is SystemExit:  # as Python's own: a thread that exits says nothing
        return
    name = args.thread.name if args.thread is not None else "(unknown)"
    _write_report(f"Exception in thread {name}:\n" + _format_exception(args.exc_type, args.exc_value,
                                                                         args.exc_traceback))


def _unraisablehook(unraisable: object) -> None:
    try:
        where = f"{unraisable.err_msg or 'Exception ignored in'}: {unraisable.object!r}"
    except Exception:  # noqa: BLE001 - an object whose repr fails: Python's hook says as little
        where = f"{unraisable.err_msg or 'Exception ignored in'}: <object repr() failed>"
    _write_report(f"{where}\n" + _format_exception(unraisable.exc_type, unraisable.exc_value,
                                                     unraisable.exc_traceback))


def _showwarning(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: object = None,
                 line: str | None = None) -> None:
    import warnings

    _write_report(warnings.formatwarning(message, category, filename, lineno, line), file)


def make_python_reports_terminal_safe() -> None:
    """What Python prints by itself made safe for the terminal and cut short (:data:`PYTHON_REPORT_CHARS`): the
    traceback of an exception nothing caught (``sys.excepthook``, and ``threading.excepthook`` for a thread's),
    of one it had to ignore (``sys.unraisablehook``: a failing ``__del__``) and a warning (``warnings.showwarning``,
    whose line is read back from the file, a policy's included). Their messages may quote anything: a stored text,
    a policy's source line or file name, what a server sent; Python's hooks printed them raw, escapes and all."""
    import threading
    import warnings

    sys.excepthook = _excepthook
    threading.excepthook = _thread_excepthook
    sys.unraisablehook = _unraisablehook
    warnings.showwarning = _showwarning


def print_failure(heading: str = "") -> None:
    """The exception being handled, with its traceback, on stderr, made safe for the terminal and cut short first
    (as Python's own reports are: :func:`_write_report`): a server's failure may quote what an untrusted client
    sent, a megabyte of it too. ``heading``: a line before it."""
    import traceback  # only where something failed

    text = traceback.format_exc()
    _write_report(f"{heading}\n{text}" if heading else text)


def plain_text(text: object) -> str:
    """Untrusted ``text`` shown as plain text in a viewer (Rerun's text documents and logs): its lines kept, and no
    escape sequence, control or bidi character (the viewer shows them as they are: a right-to-left override
    reorders what a person reads)."""
    return terminal_text(text, multiline=True)


def plot_text(text: object) -> str:
    """Untrusted ``text`` in a matplotlib title, label or legend: one line, no control characters, ``$`` escaped."""
    return terminal_text(text).replace("$", "\\$")


# Markdown's link, image, code, emphasis, heading and table punctuation, and GitHub's math delimiter ($); and, so that
# no raw "javascript:" or "onerror=" is left even as inert text, a colon or equals sign glued to a word ("step: 16",
# "a = 1" stay as written)
_MARKDOWN_PUNCTUATION = re.compile(r"[\\`*_\[\](){}#|!~$]|(?<=\w):(?=\S)|(?<=\w)=")


def markdown_text(text: object) -> str:
    """Untrusted ``text`` inline in Markdown: one line, controls removed, ``< > &`` HTML-escaped and the
    punctuation of Markdown's links, images, code spans, emphasis and tables backslash-escaped."""
    text = terminal_text(text)
    return html.escape(_MARKDOWN_PUNCTUATION.sub(r"\\\g<0>", text), quote=False)


class Markdown(str):
    """Text a viewer composed as Markdown itself (from trusted parts, or from parts it escaped): shown as is."""


def markdown_cell(value: object) -> str:
    """Text in a cell of a Markdown table: any text escaped (:func:`markdown_text`); :class:`Markdown` as it is, on
    one line, with its ``|`` escaped (GitHub's tables split cells at a ``|`` even inside a code span)."""
    if isinstance(value, Markdown):
        return value.replace("\n", " ").replace("|", "\\|")
    return markdown_text(value)


def _fence(text: str, minimum: int) -> str:
    longest = max((len(run) for run in re.findall(r"`+", text)), default=0)
    return "`" * max(minimum, longest + 1)


def markdown_code(text: object) -> Markdown:
    """``text`` as an inline code span (one line, controls removed)."""
    text = terminal_text(text)
    fence = _fence(text, 1)
    pad = " " if text.startswith("`") or text.endswith("`") or not text.strip() else ""
    return Markdown(f"{fence}{pad}{text}{pad}{fence}")


def markdown_code_block(text: object, language: str = "") -> Markdown:
    """``text`` as a fenced code block (controls removed; lines and tabs kept) whose fence no line inside can
    close."""
    text = "\t".join(terminal_text(part, multiline=True) for part in str(text).split("\t"))
    fence = _fence(text, 3)
    return Markdown(f"{fence}{language}\n{text}\n{fence}")
