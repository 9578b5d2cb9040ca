"""Shared settings of the reliability suite.

``TERRASTREAM_RELIABILITY_LONG=1`` (``make reliability``) runs the long version (>= 20 kills,
more flips). Counts of injected, detected, survived and lost faults are appended as JSON lines to
``$TERRASTREAM_RELIABILITY_REPORT`` when that variable names a file.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tiler"))  # storetools

LONG = os.environ.get("TERRASTREAM_RELIABILITY_LONG") == "1"
SEED = 20261201


def record(name: str, **counts: int) -> None:
    """Append one result line to the report file (if asked for) and print it."""
    line = json.dumps({"test": name, "long": LONG, **counts})
    print(line)
    path = os.environ.get("TERRASTREAM_RELIABILITY_REPORT")
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(line + "\n")
