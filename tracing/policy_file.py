"""Policy files: load one in the sandbox, name its version, and write new method sources back into it.

A policy file is a Python module that defines ``class Policy`` (a :class:`tracing.Module`, or decorated with
``@trace.model``), written with ``import tracing as trace`` or, unchanged from Microsoft's Trace, with
``import opto.trace as trace`` / ``from opto.trace import bundle, Module, ...`` (``tracing/trace_api.py``),
and may declare its task with upper-case module constants::

    GAME = "pong"                 # which game it plays (``--game`` may also say it)
    ROLLOUT_STEPS = 400           # traced training rollout horizon for the optimizer
    EVAL_MAX_STEPS = 4000         # evaluation cap
    FEEDBACK = {...}              # staged-feedback bands (see pipeline/optimizer/feedback.py)
    INSTRUCTION = "..."           # task statement for the optimizer's prompt

:func:`inspect_policy` reads all of that without executing anything (the parent process never runs policy
code); :func:`load_policy` executes the file in the sandbox and returns a live instance (worker processes).

A policy *version* is the whole text of the file; its id is a content hash, so the same code always has the
same id. The optimizer changes a version by replacing the text of bundled methods (:func:`replace_methods`),
which keeps everything else (imports, helpers, decorators, comments) as it was.
"""

from __future__ import annotations

import ast
import hashlib
import linecache
import re
import sys
import textwrap
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tracing import trace_api  # answers policy code's `opto.trace` imports (loaded before a worker is confined)
from tracing.bundle import Module
from tracing.capture import failing_policy_line
from tracing.sandbox import PolicyCodeError, check_source, safe_builtins, time_limit

TASK_CONSTANTS = ("GAME", "ROLLOUT_STEPS", "EVAL_MAX_STEPS", "FEEDBACK", "INSTRUCTION")
"""The module constants of a policy file that declare its task (the list above)."""

LOAD_TIME_LIMIT_S = 5.0
"""Module-level code and ``Policy()`` together must finish within this (a file that loops is refused)."""
MAX_POLICY_CHARS = 200_000
"""The longest policy file (and candidate, and code in a reply) this tool reads, ~20 times the paper's longest.
Parsing Python holds up to ~1 KB a character of degenerate code (``0\n`` repeated) and an f-string of ``{1}`` takes
time quadratic in its length, and the trusted processes parse what a worker has vetted: a megabyte held ~1 GB in
them; at this size ~200 MB and a few seconds at most."""


class PolicyLoadError(Exception):
    """A policy file that cannot be used; the message is one line that says why and where."""


def version_id(text: str) -> str:
    """Content id of a policy version: the first 16 hex digits of the SHA-256 of its text."""
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class MethodInfo:
    """A bundled method as written in the file, found without running anything."""

    name: str
    source: str
    trainable: bool
    lineno: int


@dataclass
class PolicyInfo:
    """What can be known of a policy file without executing it: its text, task constants, bundled methods.

    Produced by :func:`inspect_policy`, which the parent process uses: untrusted code only ever executes in
    worker processes (and in tests).
    """

    text: str
    name: str
    constants: dict[str, Any] = field(default_factory=dict)
    methods: list[MethodInfo] = field(default_factory=list)

    @property
    def version_id(self) -> str:
        return version_id(self.text)

    @property
    def game(self) -> str | None:
        game = self.constants.get("GAME")
        return game if isinstance(game, str) else None

    @property
    def trainable(self) -> list[MethodInfo]:
        return [m for m in self.methods if m.trainable]


@dataclass
class LoadedPolicy:
    """A policy instance built from a file's text, with the file's static description."""

    policy: Module
    info: PolicyInfo

    @property
    def text(self) -> str:
        return self.info.text

    @property
    def version_id(self) -> str:
        return self.info.version_id


def read_policy_file(path: str | Path, kind: str = "policy file") -> str:
    """The text of a policy file (or of another ``kind`` of file a policy comes from: a Trace script), with errors
    that say what to do. None is read past :data:`MAX_POLICY_CHARS`: its parse would cost this process ~1 KB a
    character."""
    if not str(path).strip():  # Path('') is '.', the current directory ("is a directory")
        raise PolicyLoadError(f"the {kind}'s path is empty; give a Python file that defines class Policy")
    p = Path(path)
    if not p.exists():
        raise PolicyLoadError(f"{kind} '{path}' does not exist")
    if p.is_dir():
        raise PolicyLoadError(f"'{path}' is a directory; give a Python file that defines class Policy")
    try:
        with p.open("rb") as f:  # no more than a policy may hold is read (4 bytes a character at most)
            data = f.read(4 * MAX_POLICY_CHARS + 1)
        text = data.decode("utf-8-sig")  # a byte-order mark (Windows editors write one) is no character of it
    except UnicodeDecodeError:
        if len(data) > 4 * MAX_POLICY_CHARS:
            text = ""  # cut mid-character: too long in any case
        else:
            raise PolicyLoadError(f"{kind} '{path}' is not UTF-8 text") from None
    if len(data) > 4 * MAX_POLICY_CHARS or len(text) > MAX_POLICY_CHARS:
        advice = "the most a policy holds" if kind == "policy file" else \
            "the most codearcade reads: put class Policy and what it uses in a file of their own"
        raise PolicyLoadError(f"{kind} '{path}' is longer than {MAX_POLICY_CHARS:,} characters, {advice}")
    return python_newlines(text)


def python_newlines(text: str) -> str:
    """``text`` with its line ends as Python reads a source file: ``\r\n`` and ``\r`` as ``\n``. A file saved
    on Windows ends its lines with ``\r\n``; kept, a method's source taken from it could not be dedented and parsed
    on its own ("unexpected indent")."""
    return text.replace("\r\n", "\n").replace("\r", "\n") if "\r" in text else text


def _bundle_call(decorators: list[ast.expr]) -> ast.expr | None:
    """The ``bundle(...)``/``trace.bundle(...)`` decorator among ``decorators``, or None."""
    for d in decorators:
        target = d.func if isinstance(d, ast.Call) else d
        if (target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)) == "bundle":
            return d
    return None


def _check_bundles(tree: ast.Module, policy_class: ast.ClassDef, name: str) -> None:
    """PolicyLoadError for bundled methods the trace cannot attribute: the trace records the calls of the bundled
    methods of class ``Policy`` itself, each trainable or not as its text says. A bundled method of a base class
    of Policy, or a trainable flag that is not written ``True`` or ``False``, played untraced and forfeited every
    traced game ("malformed trace"), and the optimizer never saw the method."""
    for node in policy_class.body:
        bundle = _bundle_call(node.decorator_list) if isinstance(node, ast.FunctionDef) else None
        flags = [kw.value for kw in bundle.keywords if kw.arg == "trainable"] if isinstance(bundle, ast.Call) else []
        literal = all(isinstance(flag, ast.Constant) and isinstance(flag.value, bool) for flag in flags)
        # a value given by position is trainable to tracing.bundle and a description to Trace's own bundle: the
        # flag must then be a keyword too
        if isinstance(bundle, ast.Call) and (not literal or (bundle.args and not flags)):
            raise PolicyLoadError(f"{name}:{node.lineno}: write @trace.bundle(trainable=True) or "
                                  f"@trace.bundle(trainable=False) on {node.name}: the trace reads the flag from the "
                                  "text")
    classes = {node.name: node for node in tree.body if isinstance(node, ast.ClassDef)}
    seen, bases = set(), [b.id for b in policy_class.bases if isinstance(b, ast.Name)]
    while bases:
        base = classes.get(bases.pop())
        if base is None or base.name in seen or base.name == "Policy":
            continue
        seen.add(base.name)
        for node in base.body:
            if isinstance(node, ast.FunctionDef) and _bundle_call(node.decorator_list) is not None:
                raise PolicyLoadError(f"{name}:{node.lineno}: {base.name}.{node.name} is bundled in a base class of "
                                      "Policy: the trace records the bundled methods of class Policy itself; define "
                                      "it in Policy")
        bases += [b.id for b in base.bases if isinstance(b, ast.Name)]


def _bundle_flags(decorators: list[ast.expr]) -> bool | None:
    """None if no decorator is ``bundle(...)``/``trace.bundle(...)``; else whether it says trainable=True."""
    for d in decorators:
        call = d if isinstance(d, ast.Call) else None
        target = call.func if call else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)
        if name == "bundle":
            for kw in call.keywords if call else []:
                if kw.arg == "trainable" and isinstance(kw.value, ast.Constant):
                    return bool(kw.value.value)
            return False
    return None


def inspect_policy(text: str, name: str = "policy.py") -> PolicyInfo:
    """Check a policy file without running it: sandbox rules, a top-level ``Policy`` class, literal task
    constants and the bundled methods of ``Policy``. Raises :class:`PolicyLoadError` with a one-line reason."""
    filename = f"<policy {name}>"
    if len(text) > MAX_POLICY_CHARS:
        raise PolicyLoadError(f"{name}: {len(text):,} characters; a policy file holds at most {MAX_POLICY_CHARS:,}")
    try:
        tree = check_source(text, filename)
    except PolicyCodeError as exc:
        raise PolicyLoadError(str(exc).replace(filename, name)) from None
    except (RecursionError, MemoryError, ValueError) as exc:  # 200 KB of `1 + 1 + ...`, NUL bytes
        raise PolicyLoadError(f"{name}: the code cannot be checked ({type(exc).__name__}: too large, too deeply "
                              "nested or not text)") from None
    constants: dict[str, Any] = {}
    policy_class = None
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == "Policy":
            policy_class = node
        elif isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            key = node.targets[0].id
            if key.isupper() and not key.startswith("_"):
                try:
                    constants[key] = ast.literal_eval(node.value)
                except ValueError:
                    pass  # computed constants are the policy's business, not the task's
    if policy_class is None:
        raise PolicyLoadError(f"{name}: no class named 'Policy' (define `class Policy(trace.Module)`)")
    _check_bundles(tree, policy_class, name)
    lines = text.splitlines(True)
    methods = []
    for node in policy_class.body:
        if isinstance(node, ast.FunctionDef):
            trainable = _bundle_flags(node.decorator_list)
            if trainable is not None:
                source = textwrap.dedent("".join(lines[node.lineno - 1 : node.end_lineno])).strip("\n") + "\n"
                methods.append(MethodInfo(node.name, source, trainable, node.lineno))
    return PolicyInfo(text, name, constants, methods)


def load_policy(text: str, name: str = "policy.py", time_limit_s: float = LOAD_TIME_LIMIT_S) -> LoadedPolicy:
    """Execute a policy file's text in the sandbox and instantiate its ``Policy``.

    Raises :class:`PolicyLoadError` with a one-line reason: syntax error, forbidden import or construct,
    an exception or time-out in module code or in ``Policy()``, no ``Policy`` class.
    """
    info = inspect_policy(text, name)
    filename = f"<policy {name}>"
    code = compile(text, filename, "exec")
    linecache.cache[filename] = (len(text), None, text.splitlines(True), filename)
    module = types.ModuleType("policy")
    namespace: dict[str, Any] = module.__dict__
    namespace["__builtins__"] = safe_builtins(trace_api)
    # the policy's own module, as an import makes one: dataclasses resolves a class's annotations (strings under
    # this module's `from __future__ import annotations`) through it, and `@dataclass` with a typed field failed
    sys.modules["policy"] = module
    try:
        with time_limit(time_limit_s, "loading the policy"):
            exec(code, namespace)
            cls = namespace.get("Policy")
            if not isinstance(cls, type):
                raise PolicyLoadError(f"{name}: 'Policy' is a {type(cls).__name__}, not a class")
            instance = cls()
    except PolicyLoadError:
        raise
    except BaseException as exc:  # noqa: BLE001 - policy code may raise anything, timeouts included
        if isinstance(exc, RuntimeError) and str(exc).startswith("Error calling __set_name__") and exc.__cause__:
            line, source = failing_policy_line(exc)  # where the class is; the error is the bundle's own
            cause = exc.__cause__
            if isinstance(cause, PolicyCodeError):  # its own words, with the policy's name for its file's
                raise PolicyLoadError(str(cause).replace(filename, name)) from None
            raise PolicyLoadError(f"{name}:{line}: {type(cause).__name__}: {cause}" if line else
                                  f"{name}: {type(cause).__name__}: {cause}") from None
        line, source = failing_policy_line(exc)
        where = f"{name}:{line}: " if line else f"{name}: "
        detail = f" (in `{source}`)" if source else ""
        raise PolicyLoadError(f"{where}{type(exc).__name__}: {exc}{detail}") from None
    if not isinstance(instance, Module):
        raise PolicyLoadError(f"{name}: Policy must subclass tracing.Module or be decorated with @trace.model")
    return LoadedPolicy(instance, info)


def _methods_by_name(tree: ast.Module) -> dict[str, ast.FunctionDef]:
    """Methods of top-level classes, by name; ``Policy``'s win over other classes' of the same name."""
    found: dict[str, ast.FunctionDef] = {}
    classes = sorted((n for n in tree.body if isinstance(n, ast.ClassDef)), key=lambda c: c.name == "Policy")
    for cls in classes:
        for node in cls.body:
            if isinstance(node, ast.FunctionDef):
                found[node.name] = node
    return found


def replace_methods(text: str, sources: dict[str, str]) -> str:
    """Return ``text`` with the ``def`` blocks of the named methods replaced by new sources.

    Decorators and everything outside the replaced blocks are kept byte for byte; each new source is
    re-indented to its method's column. Raises :class:`PolicyCodeError` for an unknown method name.
    """
    tree = ast.parse(text)
    methods = _methods_by_name(tree)
    lines = text.splitlines(True)
    spans = []
    for name, source in sources.items():
        node = methods.get(name)
        if node is None:
            raise PolicyCodeError(f"the policy has no method '{name}'")
        indent = " " * node.col_offset
        body = textwrap.indent(textwrap.dedent(source).strip("\n") + "\n", indent, lambda line: line.strip() != "")
        spans.append((node.lineno - 1, node.end_lineno, body))
    for start, end, body in sorted(spans, reverse=True):
        lines[start:end] = [body]
    return "".join(lines)


@dataclass(frozen=True)
class ExtractedPolicy:
    """The policy part of a script (:func:`policy_from_script`): the text of a policy file, and what was left out."""

    text: str
    kept: list[str]
    """Top-level names kept beside ``Policy`` (helpers and constants it uses), in file order."""
    dropped_imports: list[str]
    """Imports policy code may not make (the training loop's ``os``, ``gymnasium``, ``opto.optimizers`` ...)."""


def _statement_names(node: ast.stmt) -> list[str]:
    """The names a top-level definition binds (a def, a class, an assignment to plain names, ``+=`` and kin)."""
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    targets = node.targets if isinstance(node, ast.Assign) else \
        [node.target] if isinstance(node, (ast.AnnAssign, ast.AugAssign)) else []
    return [t.id for target in targets for t in ast.walk(target) if isinstance(t, ast.Name)]


_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+$")


def _source_lines(text: str) -> list[str]:
    """``text``'s lines with their ends, as the parser numbers them (``\n``, ``\r\n`` or ``\r`` ends a line; a
    form feed does not, as it does for ``str.splitlines``)."""
    return _LINE.findall(text)


def _segment(lines: list[str], node: ast.AST) -> str:
    """``ast.get_source_segment`` of ``node`` from lines split once (it splits the whole text again at each call:
    a script of 20,000 statements took 47 s). Column offsets are in UTF-8 bytes."""
    first, last = node.lineno - 1, node.end_lineno - 1
    if first == last:
        return lines[first].encode()[node.col_offset:node.end_col_offset].decode()
    return (lines[first].encode()[node.col_offset:].decode() + "".join(lines[first + 1:last])
            + lines[last].encode()[:node.end_col_offset].decode())


def policy_from_script(text: str, name: str = "script.py", game: str | None = None) -> ExtractedPolicy:
    """The policy file inside a Trace training script (or any module that defines ``class Policy``), found
    without running anything: the imports policy code may make, ``Policy`` and the top-level definitions it uses,
    transitively (helper functions, constants, classes), in their original order and text. Everything else — the
    environment, the optimizer, the training loop, ``if __name__ == "__main__":`` — is left out: it cannot run
    in the sandbox and is not the policy. ``game`` adds ``GAME = "<game>"`` after the imports where the script
    declares none. Raises :class:`PolicyLoadError` with a one-line reason."""
    try:
        tree = ast.parse(text, name)
    except SyntaxError as exc:
        raise PolicyLoadError(f"{name}, line {exc.lineno}: SyntaxError: {exc.msg}") from None
    except (RecursionError, MemoryError, ValueError) as exc:
        raise PolicyLoadError(f"{name}: the code cannot be read ({type(exc).__name__}: too large, too deeply "
                              "nested or not text)") from None
    definitions: dict[str, list[ast.stmt]] = {}  # every statement that binds a name, in order: `SPEED = 2` and
    for node in tree.body:  # `SPEED = SPEED * 2` (or `SPEED += 2`) both, where the last alone failed or lost one
        for bound in _statement_names(node):
            definitions.setdefault(bound, []).append(node)
    if not isinstance((definitions.get("Policy") or [None])[-1], ast.ClassDef):
        raise PolicyLoadError(f"{name}: no class named 'Policy' to take (a policy is `class Policy(trace.Module)`)")
    wanted: set[int] = set()
    pending = [*definitions["Policy"][-1:], *(node for c in TASK_CONSTANTS for node in definitions.get(c, ()))]
    while pending:
        node = pending.pop()
        if id(node) in wanted:
            continue
        wanted.add(id(node))
        used = {n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
        pending.extend(bound for u in used for bound in definitions.get(u, ()))
    lines = _source_lines(text)
    parts, kept, dropped = [], [], []
    imports_end = 0
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            # each name on its own: `import opto.trace as trace, os.path` keeps trace (the statement was dropped
            # whole, and the policy had no `trace`)
            try:
                check_source(_segment(lines, node))
                names = [node]
            except PolicyCodeError:
                names = [node] if len(node.names) == 1 else [
                    ast.Import(names=[a]) if isinstance(node, ast.Import) else
                    ast.ImportFrom(module=node.module, names=[a], level=node.level) for a in node.names]
            for one in names:
                segment = _segment(lines, node) if one is node else ast.unparse(one)
                try:
                    check_source(segment)
                except PolicyCodeError:
                    dropped.append(segment)
                    continue
                parts.append(segment + "\n")
                imports_end = len(parts)
        elif id(node) in wanted:
            first = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])])
            parts.append("\n\n" + "".join(lines[first - 1: node.end_lineno]).rstrip("\n") + "\n")
            kept.extend(n for n in _statement_names(node) if n != "Policy")
    declared = (definitions.get("GAME") or [None])[-1]
    if game is not None and declared is not None:
        try:
            stated = ast.literal_eval(declared.value) if isinstance(declared, ast.Assign) else None
        except ValueError:
            stated = None
        if stated != game:
            raise PolicyLoadError(f"{name} declares GAME = {stated!r}; leave out --game or give that game")
    elif game is not None:
        parts.insert(imports_end, f"\nGAME = {game!r}\n")
    return ExtractedPolicy("".join(parts).lstrip("\n"), kept, dropped)
