"""Every WARNING and ERROR a sim process wrote to its log, counted by kind: pure, text in.

A user must never learn from ``service.log`` what the report kept quiet about (issue 22: a
library moved aside and a fleet flying without sharing both ended in "warnings: none"). So
the report does not pick the lines it knows: it reads every line at WARNING level or above, in
the service's two formats (human lines, JSON lines), Python tracebacks and ``warnings``
module lines, and the SITL's error lines, and groups them by a stable key: the process, the
level, the logger and the message with its variable parts (numbers, paths, addresses)
masked. Lines of one kind differ only in those parts, so a flapping warning logged 40 times
is one kind with a count of 40 and its first line as the example.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

LEVELS = ("WARNING", "ERROR", "CRITICAL")
_HUMAN = re.compile(
    r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} (?P<level>[A-Z]+)\s+(?P<logger>[\w.\-]+): (?P<msg>.*)$"
)
_PY_WARNING = re.compile(r"^\S+:\d+: (?P<category>\w*Warning): (?P<msg>.*)$")
_EXCEPTION = re.compile(
    r"^(?P<type>[A-Za-z_][\w.]*(?:Error|Exception|Exit|Interrupt)\b)(?P<msg>.*)$"
)
# the SITL prints, not logs: its start line and closing counters are not warnings, any other
# "epc-sitl: ..." line is a failure it reports before exiting
# faulthandler's: the service did not end within its grace after "stopped" (bounded_exit), or
# a fatal error; the stacks that follow are in the log, the kind is the headline
_FAULT = re.compile(r"^(?:Timeout \((?P<after>[\d:.]+)\)!|Fatal Python error: (?P<fatal>.*))$")
_SITL_LINE = re.compile(r"^epc-sitl: (?!instance |counters )(?P<msg>.+)$")
# variable parts of a message, masked in this order: the key of a kind must not change with a
# path, an address, a port or a count
_MASKS = (
    # absolute paths, and relative ones ending in an extension (not "mode/arming")
    (re.compile(r"(?<![\w.])/[\w.\-+/]+|[\w.\-+]+(?:/[\w.\-+]+)+\.\w+"), "<path>"),
    (re.compile(r"0x[0-9a-fA-F]+"), "<hex>"),
    (re.compile(r"(?<![A-Za-z_])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?"), "<n>"),
)
TEMPLATE_CHARS = 160  # a key stays readable; kinds that differ only beyond this are one kind


@dataclass(frozen=True)
class LogKind:
    """One kind of logged warning or error in one process."""

    process: str  # "service", "sitl"
    level: str  # WARNING, ERROR or CRITICAL
    logger: str  # the logger's name, "traceback" or the warning's category
    template: str  # the message with its variable parts masked
    count: int
    first: str  # the first such line, as logged

    @property
    def key(self) -> str:
        return f"{self.process} {self.level} {self.logger}: {self.template}"


def template(message: str) -> str:
    """The message with numbers, paths and addresses masked, cut at TEMPLATE_CHARS."""
    for pattern, mask in _MASKS:
        message = pattern.sub(mask, message)
    return message[:TEMPLATE_CHARS]


def _json_entry(line: str) -> tuple[str, str, str] | None:
    if not line.startswith("{"):
        return None
    try:
        entry = json.loads(line)
    except ValueError:
        return None
    if not isinstance(entry, dict) or "level" not in entry:
        return None
    return str(entry["level"]).upper(), str(entry.get("logger", "")), str(entry.get("msg", ""))


def _entries(text: str) -> list[tuple[str, str, str, str]]:
    """(level, logger, message, first line) of every line of interest, in order."""
    out: list[tuple[str, str, str, str]] = []
    in_traceback = False
    for line in text.splitlines():
        if line.startswith("Traceback (most recent call last):"):
            in_traceback = True
            continue
        if in_traceback:
            if line.startswith((" ", "\t")) or not line.strip() or line.startswith("During "):
                continue
            in_traceback = False
            exc = _EXCEPTION.match(line)
            name = exc["type"] if exc else "exception"
            out.append(("ERROR", "traceback", f"{name}{exc['msg'] if exc else ': ' + line}", line))
            continue
        human = _HUMAN.match(line)
        if human:
            out.append((human["level"], human["logger"], human["msg"], line))
            continue
        entry = _json_entry(line)
        if entry is not None:
            out.append((*entry, line))
            continue
        warning = _PY_WARNING.match(line)
        if warning:
            out.append(("WARNING", warning["category"], warning["msg"], line))
            continue
        fault = _FAULT.match(line)
        if fault:
            what = (f"did not end within {fault['after']} of stopping (every thread's stack "
                    "follows in the log)" if fault["after"] else fault["fatal"])  # fmt: skip
            out.append(("ERROR", "faulthandler", what, line))
            continue
        sitl = _SITL_LINE.match(line)
        if sitl:
            out.append(("ERROR", "epc-sitl", sitl["msg"], line))
    return out


def log_kinds(text: str, process: str) -> list[LogKind]:
    """The WARNING/ERROR/CRITICAL kinds in one process's log, in order of first appearance."""
    counts: dict[tuple[str, str, str], list[str | int]] = {}
    for level, logger, message, line in _entries(text):
        if level not in LEVELS:
            continue
        key = (level, logger, template(message))
        if key in counts:
            counts[key][0] = int(counts[key][0]) + 1
        else:
            counts[key] = [1, line]
    return [
        LogKind(process, level, logger, tmpl, int(n), str(first))
        for (level, logger, tmpl), (n, first) in counts.items()
    ]
