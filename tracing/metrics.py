"""Code metrics of policy versions, as in the paper's Table 3: lines of code, cyclomatic complexity and the
deepest nesting of ``if`` statements.

Definitions (stable: stored per version in ``policy_versions``):

- ``loc``: radon's physical line count of the whole policy file; ``sloc``: its source lines (no blanks or
  comment-only lines; docstrings count).
- ``complexity``: the sum of radon's cyclomatic complexity over every method of the ``Policy`` class (a
  straight-line method counts 1; each ``if``/``elif``/loop/boolean operator adds 1).
- ``max_if_depth``: the deepest nesting of ``if`` statements inside any method; an ``elif`` chain is one
  level, a conditional expression counts like an ``if``.
Per trainable method the same three figures are stored too.
"""

from __future__ import annotations

import ast
from dataclasses import asdict, dataclass
from functools import lru_cache

from radon.complexity import cc_visit
from radon.raw import analyze


@dataclass(frozen=True)
class CodeMetrics:
    loc: int
    sloc: int
    complexity: int
    max_if_depth: int

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def max_if_depth(node: ast.AST) -> int:
    """Deepest nesting of ``if`` (and conditional expressions) below ``node``; ``elif`` does not nest."""

    def depth(n: ast.AST, level: int) -> int:
        deepest = level
        if isinstance(n, (ast.If, ast.IfExp)):
            level += 1
            deepest = level
            orelse = n.orelse if isinstance(n.orelse, list) else [n.orelse]
            children = [n.test, *(n.body if isinstance(n.body, list) else [n.body])]
            for child in children:
                deepest = max(deepest, depth(child, level))
            # an elif is the If that is the whole else-branch: same level as its parent
            if len(orelse) == 1 and isinstance(orelse[0], ast.If):
                deepest = max(deepest, depth(orelse[0], level - 1))
            else:
                for child in orelse:
                    deepest = max(deepest, depth(child, level))
            return deepest
        for child in ast.iter_child_nodes(n):
            deepest = max(deepest, depth(child, level))
        return deepest

    return depth(node, 0)


def _function_nodes(tree: ast.Module) -> dict[str, ast.FunctionDef]:
    found = {}
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == "Policy":
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    found[item.name] = item
    return found


@lru_cache(maxsize=512)  # pure; radon tokenizes the text: ~10 ms a policy, for every run or version row of it
def function_metrics(source: str) -> CodeMetrics:
    """Metrics of one method's source text (a single ``def``)."""
    raw = analyze(source)
    blocks = cc_visit(source)
    complexity = sum(b.complexity for b in blocks if type(b).__name__ == "Function" and not b.is_method) or 1
    return CodeMetrics(raw.loc, raw.sloc, complexity, max_if_depth(ast.parse(source)))


@lru_cache(maxsize=128)
def policy_metrics(text: str) -> CodeMetrics:
    """Metrics of a whole policy file (see the module docstring for the definitions)."""
    raw = analyze(text)
    classes = [b for b in cc_visit(text) if type(b).__name__ == "Class" and b.name == "Policy"]
    complexity = sum(m.complexity for m in classes[0].methods) if classes else 0
    tree = ast.parse(text)
    depth = max((max_if_depth(f) for f in _function_nodes(tree).values()), default=0)
    return CodeMetrics(raw.loc, raw.sloc, complexity, depth)
