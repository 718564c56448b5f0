"""`epc-offboard log mcap FLIGHT.csv OUT.mcap`: the per-tick flight log as MCAP.

The service writes one CSV row per position-loop tick (``[log] flight_log_path``; `sim`
writes ``DIR/vehicleK/flight.csv``). This turns it into an MCAP file that Foxglove Studio
and PlotJuggler open: one channel, topic ``/flight``, JSON messages described by a JSON
schema (one property per CSV column, numbers as numbers, ``phase`` and ``source`` as
strings), each logged at the row's vehicle time (``vehicle_t_s``, ns since the autopilot
booted). A column is a number when every row of it parses as one; a non-finite number
(never written by the service) becomes ``null``, as JSON has no NaN.

Pure file to file, no state; the ``mcap`` package (Foxglove's reference implementation)
writes and reads the container.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
from typing import Any

from mcap.writer import Writer

from epc_offboard.common.errors import EXIT_OK, UsageError

TOPIC = "/flight"
SCHEMA_NAME = "epc_offboard.FlightTick"
TIME_COLUMN = "vehicle_t_s"  # the log time of each message


def read_flight_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of a flight log; :class:`UsageError` names the file and what is wrong."""
    if not path.is_file():
        raise UsageError(f"{path}: no such flight log")
    with path.open(newline="", encoding="utf-8") as fh:
        table = list(csv.reader(fh))
    if not table or TIME_COLUMN not in table[0]:
        raise UsageError(f"{path}: not a flight log (no {TIME_COLUMN} column in the header)")
    header, rows = table[0], table[1:]
    for line, row in enumerate(rows, start=2):
        if len(row) != len(header):
            raise UsageError(f"{path}:{line}: {len(row)} cells, the header has {len(header)}")
    return header, rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _number(text: str) -> float | None:
    value = float(text)
    return value if math.isfinite(value) else None


def flight_csv_to_mcap(csv_path: Path, mcap_path: Path) -> int:
    """Write ``csv_path`` as MCAP to ``mcap_path`` (replaced whole); returns rows written."""
    header, rows = read_flight_csv(csv_path)
    numeric = [all(_is_number(r[i]) for r in rows) for i in range(len(header))]
    t_col = header.index(TIME_COLUMN)
    if not numeric[t_col]:
        raise UsageError(f"{csv_path}: {TIME_COLUMN} must be a number on every row")
    schema = {
        "title": SCHEMA_NAME,
        "description": f"one position-loop tick of epc-offboard ({csv_path.name})",
        "type": "object",
        "properties": {
            name: {"type": ["number", "null"]} if num else {"type": "string"}
            for name, num in zip(header, numeric, strict=True)
        },
    }
    tmp = mcap_path.with_name(mcap_path.name + ".tmp")
    with tmp.open("wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="epc-offboard")
        schema_id = writer.register_schema(
            name=SCHEMA_NAME, encoding="jsonschema", data=json.dumps(schema).encode()
        )
        channel_id = writer.register_channel(
            topic=TOPIC, message_encoding="json", schema_id=schema_id,
            metadata={"source": csv_path.name},
        )  # fmt: skip
        for seq, row in enumerate(rows):
            t_s = float(row[t_col])
            if not (t_s >= 0.0 and math.isfinite(t_s)):
                raise UsageError(f"{csv_path}:{seq + 2}: {TIME_COLUMN} {row[t_col]!r} is not >= 0")
            message: dict[str, Any] = {
                name: _number(cell) if num else cell
                for name, cell, num in zip(header, row, numeric, strict=True)
            }
            t_ns = round(t_s * 1e9)
            writer.add_message(
                channel_id=channel_id, log_time=t_ns, publish_time=t_ns,
                data=json.dumps(message, allow_nan=False).encode(), sequence=seq,
            )  # fmt: skip
        writer.finish()  # type: ignore[no-untyped-call]  # (mcap leaves it unannotated)
    tmp.replace(mcap_path)  # never leave a half-written file under the final name
    return len(rows)


def run_log_command(args: argparse.Namespace) -> int:
    src, out = Path(args.flight_csv), Path(args.out)
    try:
        n = flight_csv_to_mcap(src, out)
    finally:
        out.with_name(out.name + ".tmp").unlink(missing_ok=True)
    print(f"{out}: {n} ticks on topic {TOPIC} (JSON schema {SCHEMA_NAME})")
    return EXIT_OK
