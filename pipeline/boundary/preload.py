"""Warms a zygote (``pipeline/boundary/zygote.py``), the process that forks workers, so each worker starts warm.

:func:`warm` imports the modules of the zygote's tasks once: the game zygote's host task brings the rollout code
(the emulator stack, gymnasium, ALE and OCAtari's extractors, about 0.7 s, the game zygote imports right after its
hello, while the command checks its policy: the parent, which imports the same rollout code, needs none of it); the
policy zygote's tasks bring only the tracing layer, numpy and the validation code, and :func:`warm` then checks
that nothing pulled in the emulator stack (:data:`~pipeline.boundary.view.EMULATOR_PACKAGES`: a policy process
must have no emulator in memory, and cannot read one from disk either). It also makes pyarrow's first array and
IPC stream (about 0.25 s). Paying these once in the zygote instead of in every worker is what makes a fresh worker
per episode cheap.

What a zygote holds is copied at every fork (its page tables) and torn down at every worker's exit, so it
holds no more than its tasks use: :func:`warm` refuses pandas (:class:`NoPandas`), which pyarrow would
otherwise import only to ask whether a value is a DataFrame. The trusted processes that are codearcade's own do
not load it for that question either (:func:`lists_are_not_dataframes`), and do not import pyarrow for it: a
command that never touches an Arrow table (``runs``, ``sql``, ``--help``) imports neither pyarrow nor numpy.
"""

import importlib
import importlib.abc
import importlib.machinery
import sys
from typing import Any, Iterable


class NoPandas(importlib.abc.MetaPathFinder):
    """Refuses ``import pandas`` in this process. pyarrow imports pandas (0.3 s, 25 MB of heap) the first time it
    checks whether an array's input is a DataFrame; no zygote task ever hands it one (and policy code may not
    import pandas: ``tracing/sandbox.py``). Without it a zygote's fork and a worker's exit each cost ~2-4 ms
    less, per episode and per process (measured: the policy zygote's heap 57 -> 33 MB, the game's 126 -> 102)."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError("pandas is not loaded in codearcade's worker processes")
        return None


def lists_are_not_dataframes() -> None:
    """Have pyarrow ask whether a value is a DataFrame once, with pandas refused: it asks only once, and from then
    on takes a Python list for a list without loading pandas (0.3-0.45 s of a command's start here, 25 MB). For
    codearcade's own trusted processes (the command line's, a batch's runs), which hand pyarrow lists, never a
    pandas object; an explicit conversion (``Table.to_pandas``) still imports pandas, and a process that has
    pandas already is left as it is. The zygotes refuse pandas for good (:func:`warm`).

    Asked now if pyarrow is imported, else as soon as it is (:class:`_AskWhenImported`): importing pyarrow here
    cost every command ~0.07 s, numpy's import with it, whether it used an Arrow table or not."""
    if "pyarrow" in sys.modules:
        _ask_with_pandas_refused(sys.modules["pyarrow"])
    elif not any(isinstance(finder, _AskWhenImported) for finder in sys.meta_path):
        sys.meta_path.insert(0, _AskWhenImported())


def _ask_with_pandas_refused(pa: Any) -> None:
    if "pandas" in sys.modules:
        return
    refusal = NoPandas()
    sys.meta_path.insert(0, refusal)
    try:
        pa.array([0])
    finally:
        sys.meta_path.remove(refusal)


class _AskWhenImported(importlib.abc.MetaPathFinder):
    """Finds pyarrow as Python would (on ``sys.path``) and, once its package has run, has it ask its DataFrame
    question (:func:`_ask_with_pandas_refused`), before anything of this process hands it a list. It then leaves
    ``sys.meta_path``."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != "pyarrow":
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return None
        run = spec.loader.exec_module  # the loader is this spec's own: wrapping it changes no other import

        def exec_module(module: Any) -> None:
            run(module)
            if self in sys.meta_path:
                sys.meta_path.remove(self)
            _ask_with_pandas_refused(module)

        spec.loader.exec_module = exec_module
        return spec


def warm(modules: Iterable[str], no_emulator: bool = False) -> None:
    """Import ``modules`` (by name: they are the tasks', some above this package) and initialise pyarrow, pandas
    refused (:class:`NoPandas`); with ``no_emulator``, raise ImportError if that loaded any of
    :data:`EMULATOR_PACKAGES`."""
    import pyarrow as pa

    from pipeline.boundary.view import EMULATOR_PACKAGES
    from pipeline.boundary.wire import arrow_frame
    from tracing.capture import NodeRecorder

    if not any(isinstance(finder, NoPandas) for finder in sys.meta_path):
        sys.meta_path.insert(0, NoPandas())
    for name in modules:
        importlib.import_module(name)
    arrow_frame(NodeRecorder().table())  # pyarrow initialises its kernels (and the IPC writer) lazily on first use
    pa.ipc  # noqa: B018
    loaded = sorted({name.split(".")[0] for name in sys.modules} & set(EMULATOR_PACKAGES))
    if no_emulator and loaded:
        raise ImportError(f"the policy zygote must not load {', '.join(loaded)}")
