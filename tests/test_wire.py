"""The parent's checks of what a worker sends (pipeline/boundary/wire.py, and an episode's fields in
pipeline/play/episodes.py): anything off is a BadMessage, never accepted."""

from __future__ import annotations

import pyarrow as pa
import pytest

from pipeline.boundary import wire
from pipeline.play import episodes
from pipeline.play.rollout import run_episode
from pipeline.play.spec import EpisodeSpec
from tests.conftest import pong_policy
from tracing.capture import NODE_SCHEMA
from tracing.steps import STEP_SCHEMA


@pytest.fixture(scope="module")
def played():
    spec = EpisodeSpec("run.0.eval.0", "run", "pong", pong_policy("return 0"), "v", max_steps=5)
    outcome = run_episode(spec)
    return spec, episodes.episode_to_json(outcome.episode), outcome.steps


def _decode(spec, row, steps, nodes=None):
    return episodes.episode_from_worker(spec, row, steps, nodes)


def test_a_genuine_answer_round_trips(played):
    spec, row, steps = played
    frames = wire.FrameReader().feed(wire.json_frame({"kind": "result", "episode": row}) + wire.arrow_frame(steps))
    assert [k for k, _ in frames] == [b"J", b"A"]
    msg = wire.parse_json(frames[0][1])
    table = wire.parse_arrow(frames[1][1], STEP_SCHEMA)
    outcome = _decode(spec, msg["episode"], table)
    assert outcome.episode["episode_id"] == spec.episode_id and outcome.episode["length"] == 5
    assert outcome.steps.equals(steps)


@pytest.mark.parametrize("change, fragment", [
    ({"episode_id": "other"}, "answered for episode"),
    ({"game": "breakout"}, "game"),
    ({"end_reason": "tampered"}, "end reason"),
    ({"end_reason": "won"}, "end reason"),
    ({"length": True}, "length"),
    ({"length": 5.0}, "length"),
    ({"length": 10**9}, "length"),
    ({"length": 4}, "step rows"),
    ({"length": 3, "end_reason": "policy_error"}, "step rows"),
    ({"lives_lost": -1}, "lives_lost"),
    ({"return": "1e9"}, "return"),
    ({"return": None}, "return"),
    ({"duration_s": [1]}, "duration_s"),
    ({"error": {"x": 1}}, "error"),
    ({"started_at": "yesterday"}, "started_at"),
], ids=lambda v: str(v))
def test_a_field_out_of_place_is_refused(played, change, fragment):
    spec, row, steps = played
    with pytest.raises(wire.BadMessage, match=fragment):
        _decode(spec, {**row, **change}, steps)


def test_what_the_worker_cannot_decide_comes_from_the_spec(played):
    spec, row, steps = played
    outcome = _decode(spec, {**row, "seed": 99, "run_id": "forged", "policy_version_id": "forged"}, steps)
    assert (outcome.episode["seed"], outcome.episode["run_id"], outcome.episode["policy_version_id"]) == (0, "run", "v")


def test_tables_of_another_schema_or_broken_streams_are_refused(played):
    spec, row, steps = played
    with pytest.raises(wire.BadMessage, match="schema"):
        wire.parse_arrow(wire.arrow_frame(pa.table({"step": [0, 1]}))[wire.HEADER.size:], STEP_SCHEMA)
    with pytest.raises(wire.BadMessage, match="schema"):
        wire.parse_arrow(wire.arrow_frame(steps)[wire.HEADER.size:], NODE_SCHEMA)
    payload = wire.arrow_frame(steps)[wire.HEADER.size:]
    with pytest.raises(wire.BadMessage, match="malformed Arrow"):
        wire.parse_arrow(payload[: len(payload) // 2], STEP_SCHEMA)
    with pytest.raises(wire.BadMessage, match="expected schema"):  # refused before anything is decoded
        wire.parse_arrow(b"\x80\x03cposix\nsystem\n", STEP_SCHEMA)  # a pickle is not an Arrow stream
    renumbered = steps.set_column(0, "step", pa.array([3, 1, 2, 0, 4], pa.int32()))
    with pytest.raises(wire.BadMessage, match="numbered"):
        _decode(spec, row, renumbered)
    untraced = _decode(spec, row, steps, NODE_SCHEMA.empty_table())  # the policy's rows: its error, not a crash
    assert (untraced.end_reason, untraced.nodes) == ("policy_error", None)
    assert untraced.episode["error"] == "malformed trace: node rows for an episode that is not traced"


def _stream(table, batches=1, **options) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema, options=pa.ipc.IpcWriteOptions(**options)) as writer:
        for _ in range(batches):
            writer.write_table(table)
    return sink.getvalue().to_pybytes()


def test_an_arrow_stream_is_bounded_before_it_is_decoded(played):
    """Compressed batches and dictionaries are refused from their headers, batches and rows counted before any
    body is read; an uncompressed stream is read in place."""
    _, _, steps = played
    bomb = pa.table({"s": pa.array(["x" * 2**20] * 4)})
    payload = _stream(bomb, compression="zstd")
    assert len(payload) < 2**16  # 4 MiB of strings
    with pytest.raises(wire.BadMessage, match="compressed"):
        wire.parse_arrow(payload, bomb.schema)
    coded = pa.table({"s": pa.array(["a", "b"]).dictionary_encode()})
    with pytest.raises(wire.BadMessage, match="schema"):
        wire.parse_arrow(_stream(coded), pa.schema([("s", pa.string())]))
    with pytest.raises(wire.BadMessage, match="record batches"):
        wire.parse_arrow(_stream(steps.slice(0, 1), batches=wire.MAX_BATCHES + 1), STEP_SCHEMA)
    with pytest.raises(wire.BadMessage, match="more than 4 rows"):
        wire.parse_arrow(_stream(steps), STEP_SCHEMA, max_rows=4)
    payload = _stream(bomb)
    before = pa.total_allocated_bytes()
    table = wire.parse_arrow(payload, bomb.schema, max_rows=4)
    assert pa.total_allocated_bytes() - before < 2**16 and table.equals(bomb)  # slices of the payload


def test_frames_are_capped_and_kinds_checked():
    with pytest.raises(wire.BadMessage, match="over the limit"):
        wire.FrameReader().feed(wire.HEADER.pack(b"J", wire.MAX_JSON + 1))
    with pytest.raises(wire.BadMessage, match="over the limit"):
        wire.FrameReader().feed(wire.HEADER.pack(b"A", wire.MAX_ARROW + 1))
    with pytest.raises(wire.BadMessage, match="unknown frame kind"):
        wire.FrameReader().feed(b"\x80\x04\x95\x00\x00\x00\x00")  # the start of a pickle
    for payload in (b"[1, 2]", b'{"no": "kind"}', b"{" * 100_000, b'{"kind": "result", "x": NaN}', b"\xff"):
        with pytest.raises(wire.BadMessage):
            wire.parse_json(payload)
    reader = wire.FrameReader()
    frame = wire.json_frame({"kind": "progress", "n": 3})
    assert reader.feed(frame[:3]) == [] and reader.feed(frame[3:]) == [(b"J", frame[wire.HEADER.size:])]


@pytest.mark.parametrize("message, fragment", [
    ({"kind": "actions", "actions": [0, 3]}, "unexpected message kind"),
    ({"kind": "progress", "n": -1}, "non-negative"),
    ({"kind": "progress", "n": 2.5}, "non-negative"),
    ({"kind": "progress"}, "non-negative"),
    ({"kind": "exec", "code": "import os"}, "unexpected message kind"),
], ids=lambda v: str(v)[:60])
def test_each_message_kind_has_its_fields_checked(message, fragment):
    with pytest.raises(wire.BadMessage, match=fragment):
        wire.parse_message(wire.json_frame(message)[wire.HEADER.size:])


def test_well_formed_messages_pass_and_error_text_is_made_text():
    def parse(message):
        return wire.parse_message(wire.json_frame(message)[wire.HEADER.size:])

    assert parse({"kind": "progress", "n": 250})["n"] == 250
    assert parse({"kind": "error", "error": {"not": "text"}})["error"] == "(no reason given)"
    assert parse({"kind": "error", "error": "  x" * 10_000})["error"] == ("x" + "  x" * 9_999)[:wire.MAX_TEXT]
    assert wire.text_answer({"kind": "result", "reason": "y" * (wire.MAX_TEXT + 5), "other": None}) == \
        {"reason": "y" * wire.MAX_TEXT, "other": None}
    with pytest.raises(wire.BadMessage, match="not text"):
        wire.text_answer({"kind": "result", "reason": 3})


def _frames_for_pieces() -> list[bytes]:
    nodes = wire.raw_arrow_frame(bytes(range(256)) * 400)  # 100 KB: a large frame, read in pieces
    return [wire.json_frame({"kind": "progress", "n": i}) for i in range(3)] + [nodes, nodes,
                                                                                wire.json_frame({"kind": "result"})]


@pytest.mark.parametrize("piece", [1, 3, 1000, 65_536, 10**7])
def test_frames_arriving_in_any_pieces_come_out_whole(piece):
    frames = _frames_for_pieces()
    stream = b"".join(frames)
    reader, got = wire.FrameReader(), []
    for at in range(0, len(stream), piece):
        got.extend(reader.feed(stream[at:at + piece]))
    assert got == [(frame[:1], frame[wire.HEADER.size:]) for frame in frames]
    assert reader.held == 0


def test_the_policy_channel_reads_small_and_large_frames_whole_and_caps_them():
    import socket
    import threading

    from pipeline.boundary.policy import Channel

    frames = _frames_for_pieces() + [wire.raw_arrow_frame(b"x" * 3 * 2**20), wire.json_frame({"kind": "done"})]
    host, policy = socket.socketpair()
    sender = threading.Thread(target=lambda: policy.sendall(b"".join(frames)))
    sender.start()
    channel = Channel(host)
    got = [channel.receive(wire.MAX_ARROW) for _ in frames]
    sender.join()
    assert got == [(frame[:1], frame[wire.HEADER.size:]) for frame in frames]
    policy.sendall(wire.raw_arrow_frame(b"y" * 100_000))
    with pytest.raises(ValueError, match="over the limit"):
        channel.receive(99_999)
    policy.close()
    host.close()


def _handed_over():
    """A host's and a policy process's channel (in this process) after the go-ahead: (host, policy, the socket's
    ends, the go-ahead's payload as the policy read it)."""
    import socket

    from pipeline.boundary.policy import Channel

    host_end, policy_end = socket.socketpair()
    host, policy = Channel(host_end, timed=True), Channel(policy_end, pipes_from_host=True)
    host.send_handing_over({"op": "go", "cpu": None}, within=5)
    kind, payload = policy.receive(wire.MAX_JSON)
    return host, policy, (host_end, policy_end), (kind, payload)


def test_the_go_ahead_hands_the_policy_process_two_pipes_and_every_frame_after_it_goes_over_them():
    import os
    import stat

    host, policy, (host_end, policy_end), go = _handed_over()
    assert go == (b"J", b'{"op":"go","cpu":null}')
    assert host.piped and policy.piped
    ends = [host.read_fd, host.write_fd, policy.read_fd, policy.write_fd]
    assert all(stat.S_ISFIFO(os.fstat(fd).st_mode) for fd in ends) and len(set(ends)) == 4
    assert host_end.fileno() == policy_end.fileno() == -1, "the socket is let go at the hand-over"
    frames = _frames_for_pieces() + [wire.raw_arrow_frame(b"x" * 3 * 2**20), wire.json_frame({"kind": "done"})]
    import threading

    sender = threading.Thread(target=lambda: [policy.write_all(frame) for frame in frames])
    sender.start()
    got = [host.receive(wire.MAX_ARROW, within=10) for _ in frames]
    sender.join()
    assert got == [(frame[:1], frame[wire.HEADER.size:]) for frame in frames]
    host.send(b"O", b"obs" * 1000, within=5)
    assert policy.receive(wire.MAX_ARROW) == (b"O", b"obs" * 1000)
    with pytest.raises(TimeoutError):  # nothing more was sent
        host.receive(wire.MAX_JSON, within=0.2)
    host.close()
    policy.close()


def test_the_host_reads_the_end_of_the_pipe_when_the_policy_process_is_gone_and_leaks_no_descriptor():
    import os

    host, policy, _, _ = _handed_over()
    held = [host.read_fd, host.write_fd]
    policy.close()  # as when the policy process dies: no other process holds its ends
    with pytest.raises(EOFError):
        host.receive(wire.MAX_JSON, within=5)
    with pytest.raises(OSError):  # EPIPE: SIGPIPE is ignored in a host, as in this process
        host.send(b"O", b"obs", within=5)
    host.close()  # a kept host plays another episode next, with another policy process
    for fd in held:
        with pytest.raises(OSError):
            os.fstat(fd)


def test_a_host_never_waits_past_its_deadline_on_a_policy_process_that_stops_reading():
    import time

    host, policy, _, _ = _handed_over()
    t0 = time.monotonic()
    with pytest.raises(TimeoutError):  # the pipe fills: 64 KiB, then nothing is read
        for _ in range(1_000):
            host.send(b"O", b"o" * 8_000, within=0.3)
    assert time.monotonic() - t0 < 2
    host.close()
    policy.close()


def test_an_end_before_any_go_ahead_is_read_on_the_socket():
    import socket

    from pipeline.boundary.policy import Channel

    host_end, policy_end = socket.socketpair()
    host, policy = Channel(host_end, timed=True), Channel(policy_end, pipes_from_host=True)
    host.send_json({"op": "end", "more": False}, within=5)
    assert policy.receive(wire.MAX_JSON) == (b"J", b'{"op":"end","more":false}')
    assert not policy.piped
    policy.send_json({"kind": "done", "nodes": False})
    assert host.receive(wire.MAX_JSON, within=5) == (b"J", b'{"kind":"done","nodes":false}')
    host.close()
    policy.close()
