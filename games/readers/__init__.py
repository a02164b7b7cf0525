"""OCAtari's RAM readers redone where they are slow: the same objects, at a fraction of the cost.

One module per game (and :func:`empty_slot`, which they share), each with one function that is that game's
``Game.detect`` (``games.base.fast_reader``, imported on first use): ``detect_<game>(objects, ram)`` leaves
OCAtari's object list exactly as ``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), name, False)``
would (the same classes in the same slots, the same positions, sizes, colours, previous positions and visibility),
with ``ram`` as ALE gives it (uint8). Bare OCAtari pays its readers every step, so they are the one place where
``eval`` can win time back against it (docs/benchmarks.md, issue 40).

- :mod:`games.readers.breakout`: a gather of RAM bits and runs from the bitmap's edges (~100 µs a step -> ~8).
- :mod:`games.readers.space_invaders`: aliens re-derived when their bitmap changes, moved when they move (~46 -> ~2.2).
- :mod:`games.readers.seaquest`: each slot visited once, on ints, its empty slots' NoObjects kept (~26 -> ~4).
- :mod:`games.readers.asterix`: OCAtari's reader on ints, keeping the ~24 objects it makes anew a step (~15 -> ~4).
- :mod:`games.readers.qbert`: OCAtari's reader on ints, its loops as tables, its state in its globals (~10 -> ~2.7).
- :mod:`games.readers.freeway`: OCAtari's reader on ints, its setters' one assignment written out (~5.5 -> ~1.8).
- :mod:`games.readers.pong`: OCAtari's reader on ints, keeping the NoObjects it makes anew a step (~3.2 -> ~1.0).

tests/test_readers.py (Breakout, Space Invaders) and ``tests/test_readers_<game>.py`` compare each with OCAtari's on
played and random RAMs, object list against object list (``tests/reader_equality.py``).
"""

from ocatari.ram.game_objects import NoObject


def empty_slot(objects: list, slot: int) -> None:
    """``objects[slot] = NoObject()``, as OCAtari's readers empty a slot at every step, keeping the NoObject already
    there while it is still equal to a new one (no previous position: the environment's first observation gives every
    slot one, and from then on OCAtari's fresh NoObject differs from it)."""
    obj = objects[slot]
    if obj.__class__ is not NoObject or obj._prev_xy is not None:
        objects[slot] = NoObject()
