"""How the benchmarks record a run: the command that produced it and when, then its results."""

import json
import sys
from datetime import UTC, datetime
from pathlib import Path


def run_header() -> dict[str, str]:
    """`command` (as typed, from the repository root) and `when` (UTC) of this run."""
    script = Path(sys.argv[0]).name
    return {
        "command": " ".join([f"python bench/{script}", *sys.argv[1:]]),
        "when": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def write_record(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1))
    print(f"wrote {path}")
