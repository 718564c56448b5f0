"""`epc-offboard log mcap`: the per-tick flight log as MCAP, read back with mcap's reader."""

from __future__ import annotations

import csv
import json

import pytest
from mcap.reader import make_reader

from epc_offboard.cli import main
from epc_offboard.service.flightlog import FLIGHT_LOG_COLUMNS


def _row(k: int) -> list[str]:
    """Tick k as the service writes it: 4 and 5 decimals, negative and tiny values too."""
    row = []
    for i, name in enumerate(FLIGHT_LOG_COLUMNS):
        if name == "phase":
            row.append(["streaming", "offboard", "landing"][k % 3])
        elif name == "source":
            row.append(["hit", "solved", "intermediate"][k % 3])
        elif name in ("t_s", "vehicle_t_s"):
            row.append(f"{3.65 + 0.01 * k:.4f}")
        else:
            row.append(f"{(i - 10) * 0.123457 + k * 1e-5:.5f}")
    return row


def _write_csv(path, rows):
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(FLIGHT_LOG_COLUMNS)
        writer.writerows(rows)
    return path


def read_mcap(path):
    """[(schema, channel, log_time_ns, decoded JSON)] in file order."""
    with path.open("rb") as fh:
        return [
            (schema, channel, message.log_time, json.loads(message.data))
            for schema, channel, message in make_reader(fh).iter_messages()
        ]


def test_round_trip_same_values_and_times(tmp_path, capsys):
    rows = [_row(k) for k in range(50)]
    src = _write_csv(tmp_path / "flight.csv", rows)
    out = tmp_path / "flight.mcap"
    assert main(["log", "mcap", str(src), str(out)]) == 0
    assert "50 ticks on topic /flight" in capsys.readouterr().out

    got = read_mcap(out)
    assert len(got) == len(rows)
    schema, channel, _, _ = got[0]
    assert schema.encoding == "jsonschema"
    assert channel.topic == "/flight"
    assert channel.message_encoding == "json"
    properties = json.loads(schema.data)["properties"]
    assert list(properties) == FLIGHT_LOG_COLUMNS
    assert properties["phase"] == {"type": "string"}
    assert properties["pos_n_m"] == {"type": ["number", "null"]}
    for row, (_, _, log_time_ns, message) in zip(rows, got, strict=True):
        assert list(message) == FLIGHT_LOG_COLUMNS
        for name, cell in zip(FLIGHT_LOG_COLUMNS, row, strict=True):
            want = cell if name in ("phase", "source") else float(cell)
            assert message[name] == want, name
        assert log_time_ns == round(float(row[1]) * 1e9)


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("a,b\n1,2\n", "no vehicle_t_s column"),
        ("t_s,vehicle_t_s\n1,2,3\n", ":2: 3 cells"),
        ("t_s,vehicle_t_s\n1,soon\n", "vehicle_t_s must be a number"),
        ("t_s,vehicle_t_s\n1,-1\n", "is not >= 0"),
    ],
)
def test_a_file_that_is_not_a_flight_log_is_refused(tmp_path, capsys, text, named):
    src = tmp_path / "flight.csv"
    src.write_text(text)
    out = tmp_path / "flight.mcap"
    assert main(["log", "mcap", str(src), str(out)]) == 2
    err = capsys.readouterr().err
    assert str(src) in err
    assert named in err
    assert list(tmp_path.iterdir()) == [src]  # no output, no temporary file left
