"""Read .rrd files back with the Rerun SDK and print their content as JSON (used by tests/test_rerun.py).

Run as a separate process on purpose: the test process forks episode workers, and the Rerun SDK starts Rust
threads when imported, so the tests keep it out of their own process.

``python tests/rrd_dump.py FILE.rrd ...`` prints ``{file: {"properties": {...}, "static": {column: value},
"timelines": {timeline: {column: {index: value}}}}}``; values are JSON-friendly (lists, numbers, strings;
blobs as their SHA-256).
"""

from __future__ import annotations

import hashlib
import json
import sys

from rerun.chunk import RrdReader


def _plain(value):
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray)):
        return "sha256:" + hashlib.sha256(value).hexdigest()
    if getattr(value, "dtype", None) is not None and value.dtype == "uint8" and value.ndim == 1:
        return "sha256:" + hashlib.sha256(value.tobytes()).hexdigest()  # a blob (PNG frame)
    if hasattr(value, "tolist"):
        return _plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, float) and value != value:
        return "NaN"
    return value


def dump(path: str) -> dict:
    store = RrdReader(path).stream().collect()
    summary = store.summary()
    timelines = sorted({t for line in summary.splitlines() if "timelines=[" in line
                        for t in line.split("timelines=[", 1)[1].split("]", 1)[0].replace("'", "").split(", ") if t})
    out: dict = {"properties": {}, "static": {}, "timelines": {}}
    props = store.reader(None, contents="/__properties/**").to_pandas()
    for column in props.columns:
        if column.startswith("property:") and len(props):
            value = _plain(props[column].iloc[0])
            out["properties"][column[len("property:"):]] = value[0] if isinstance(value, list) and len(value) == 1 else value
    static = store.reader(None).to_pandas()
    for column in static.columns:
        if column not in timelines and not column.startswith("property:") and len(static):
            out["static"][column] = _plain(static[column].iloc[0])
    for timeline in timelines:
        df = store.reader(timeline).to_pandas()
        columns: dict = {}
        for column in df.columns:
            if column in timelines or column in out["static"] or column.startswith("property:"):
                continue
            values = {}
            for index, value in zip(df[timeline], df[column]):
                if value is not None:
                    values[str(int(index))] = _plain(value)
            if values:
                columns[column] = values
        out["timelines"][timeline] = columns
    return out


if __name__ == "__main__":
    json.dump({path: dump(path) for path in sys.argv[1:]}, sys.stdout)
