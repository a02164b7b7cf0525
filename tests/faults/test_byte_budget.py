"""One byte budget per episode (issue 38, items 1 and 5): the fourth outside round's classes, each sent by a policy
process through ``codearcade eval --trace --rerun DIR`` (and one through ``optimize``), measured by effect.

Each attack passed the shape checks before and made the trusted side pay far more than it sent:

- **shared metadata**: a 1 MB key/value entry that the schema's vector points at 1,000 times (the parent peaked at
  1,285 MB, the game host with ``--rerun`` at 1,170 MB): the schema is now compared byte for byte, unparsed;
- **shared fields**: 400 KB of schema whose fields vector points at one long-named field 16,000 times (738 MB);
- **widening**: 64 MB of int16 ``lines_run`` (1,130 MB in the parent, 1,608 MB in the host, episode stored):
  now over the episode's byte budget, and checked at int16 where it is within it;
- **characters, not bytes**: 16,000 astral characters a value (the store grew by 45 MB over an honest episode):
  caps are in UTF-8 bytes, and the node rows of an episode within its budget;
- **parsed on write**: ``[{},{},…]`` values (the write path's JSON cast took +718 MB).

Each must leave the ``codearcade`` process and the game host under 600 MB (peaks: each one's ``VmHWM``), the
episode an accepted one or a recorded policy error, and the store no larger than an honest episode's plus the
budget. A value that fits the budget is accepted and stored whole.
"""

from __future__ import annotations

import json

import pytest

from pipeline.boundary.nodes import node_budget
from tests.faults import test_bounded_frames
from tests.faults.test_bounded_frames import (
    LIMIT_MB,
    _episode,
    _eval,
    attack,
    optimize_with_forged_candidate,
)

honest_store = test_bounded_frames.honest_store  # the fixture: the store after an honest traced 5-step episode

SHARE = """
def share(message, path, struct=mods['struct']):
    meta = bytearray(message[8:])
    def field(table, index):
        vtable = table - struct.unpack_from('<i', meta, table)[0]
        if 4 + 2 * index + 2 > struct.unpack_from('<H', meta, vtable)[0]:
            return None
        return table + struct.unpack_from('<H', meta, vtable + 4 + 2 * index)[0]
    table = struct.unpack_from('<I', meta, 0)[0]
    for index in path[:-1]:
        at = field(table, index)
        table = at + struct.unpack_from('<I', meta, at)[0]
    at = field(table, path[-1])
    vector = at + struct.unpack_from('<I', meta, at)[0]
    first = vector + 4 + struct.unpack_from('<I', meta, vector + 4)[0]
    for i in range(1, struct.unpack_from('<I', meta, vector)[0]):
        struct.pack_into('<I', meta, vector + 4 + 4 * i, first - (vector + 4 + 4 * i))
    return message[:8] + bytes(meta)
def batches(table, pa=pa):
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()[len(table.schema.serialize().to_pybytes()):]
"""

SHARED_METADATA = SHARE + """
def forged(table, pa=pa, wire=wire, share=share, batches=batches):
    metadata = {b'k0': b'v' * 2**20}
    metadata.update({b'k%d' % i: b'' for i in range(1, 1000)})
    message = share(table.schema.with_metadata(metadata).serialize().to_pybytes(), (2, 2))
    payload = message + batches(table)
    return wire.HEADER.pack(b'A', len(payload)) + payload
"""

SHARED_FIELDS = SHARE + """
def forged(table, pa=pa, wire=wire, share=share, batches=batches):
    fields = [pa.field('f' * 100_000, pa.int8())] + [pa.field('f%d' % i, pa.int8()) for i in range(1, 16_000)]
    payload = share(pa.schema(fields).serialize().to_pybytes(), (2, 1)) + batches(table)
    return wire.HEADER.pack(b'A', len(payload)) + payload
"""

WIDE_LINES = """
def forged(table, pa=pa, real_frame=real_frame, np=mods['numpy']):
    n = table.num_rows
    per_row = 32 * 2**20 // n  # 64 MB of int16 in all
    flat = pa.array(np.ones(per_row * n, dtype=np.int16))
    offsets = pa.array(np.arange(0, (n + 1) * per_row, per_row, dtype=np.int32))
    column = table.schema.get_field_index('lines_run')
    return real_frame(table.set_column(column, 'lines_run', pa.ListArray.from_arrays(offsets, flat)))
"""


def values(text: str, rows_per_step: int) -> str:
    """Node rows whose every output is ``text`` (a Python expression), ``rows_per_step`` calls of select_action a
    step."""
    return f"""
def forged(table, pa=pa, real_frame=real_frame):
    steps = sorted(set(table.column('step').to_pylist()))
    n = len(steps) * {rows_per_step}
    columns = {{f.name: pa.nulls(n, f.type) for f in table.schema}}
    columns.update(step=pa.array([s for s in steps for _ in range({rows_per_step})], pa.int32()),
                   call_index=pa.array(list(range({rows_per_step})) * len(steps), pa.int16()),
                   function=pa.array(['select_action'] * n), trainable=pa.array([True] * n),
                   inputs=pa.array(['{{}}'] * n), output=pa.array([{text}] * n), duration_us=pa.array([1] * n, pa.int64()),
                   parents=pa.array([[]] * n, pa.list_(pa.int16())))
    return real_frame(pa.table(columns, schema=table.schema))
"""


ASTRAL = values("'\"' + '\\U0001F600' * 16_000 + '\"'", 100)
OBJECTS = values("'[' + ','.join(['{}'] * 5_333) + ']'", 400)
WITHIN = values("'\"' + '\\U0001F600' * 3_900 + '\"'", 10)
"""15.6 KB values (under the 16,000-byte cap a stored value has), 50 of them: within the budget of a 5-step
episode, so accepted and stored whole."""


@pytest.mark.slow
@pytest.mark.parametrize("forge, reason", [
    (SHARED_METADATA, "expected schema"), (SHARED_FIELDS, "expected schema"), (WIDE_LINES, "budget"),
    (ASTRAL, "bytes"), (OBJECTS, "budget"), (WITHIN, None),
], ids=["shared metadata", "shared fields", "widening", "astral characters", "parsed on write", "within budget"])
def test_each_class_costs_at_most_the_budget(forge, reason, store, write_policy, honest_store, tmp_path):
    path = write_policy(attack(forge))
    code, out, err, parent_mb, host_mb = _eval(path, store, "--trace", "--rerun", str(tmp_path / "rrd"))
    assert "Traceback" not in err, err[-3000:]
    assert parent_mb < LIMIT_MB and host_mb < LIMIT_MB, (parent_mb, host_mb)
    episode = _episode(store)
    grown = store.path.stat().st_size - honest_store
    print(f"peaks: parent {parent_mb:.0f} MB, host {host_mb:.0f} MB; store {grown / 2**20:+.2f} MB")  # for docs
    assert grown <= node_budget(5), (grown, node_budget(5))
    if reason is None:  # within the budget: accepted, its rows stored whole
        assert code == 0 and episode["end_reason"] == "truncated", (episode, err[-2000:])
        assert store.query("SELECT count(*) FROM nodes") == [(50,)]
        assert store.query("SELECT max(strlen(output::VARCHAR)) FROM nodes") == [(15_602,)]
    else:
        assert code == 1 and episode["end_reason"] == "policy_error", (episode, err[-2000:])
        assert episode["error"].startswith("malformed trace") and reason in episode["error"], episode
        assert store.query("SELECT count(*) FROM nodes") == [(0,)]
        assert store.query("SELECT count(*) FROM steps") == [(5,)]  # the host's steps are kept
    assert json.loads(out)["episodes"][0]["end_reason"] == episode["end_reason"]


@pytest.mark.slow
@pytest.mark.parametrize("forge", [SHARED_METADATA, WIDE_LINES], ids=["shared metadata", "widening"])
def test_optimize_goes_on_past_a_candidate_over_its_budget(forge, store, scripted, tmp_path):
    code, out, err, parent_mb, host_mb = optimize_with_forged_candidate(forge, store, scripted, tmp_path)
    assert code == 0 and json.loads(out)["status"] == "finished", err[-3000:]
    assert parent_mb < LIMIT_MB and host_mb < LIMIT_MB, (parent_mb, host_mb)
    refused = store.query("SELECT error FROM episodes WHERE traced AND iteration = 1")
    assert refused and all(error.startswith("malformed trace") for (error,) in refused), refused
    assert store.query("SELECT count(*) FROM episodes WHERE iteration = 0")[0][0] >= 1  # the starter's, kept
