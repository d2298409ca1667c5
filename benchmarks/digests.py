"""Digests of a run's poses, loops and graph, to prove a refactoring changed no behaviour.

Timing fields (``t_*``) of loops.jsonl are dropped before hashing: they measure the machine.
Usage: python benchmarks/digests.py RUN [RUN ...]
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path


def _loops_bytes(path: Path) -> bytes:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip():
            row = {k: v for k, v in json.loads(line).items() if not k.startswith("t_")}
            rows.append(json.dumps(row, sort_keys=True))
    return "\n".join(rows).encode()


def digests(run: Path) -> dict[str, str]:
    out = {}
    for path in sorted(run.glob("poses_*.txt")) + [run / "graph.g2o", run / "loops.jsonl"]:
        if not path.is_file():
            continue
        data = _loops_bytes(path) if path.name == "loops.jsonl" else path.read_bytes()
        out[path.name] = hashlib.sha256(data).hexdigest()[:16]
    return out


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    for arg in argv:
        for name, digest in digests(Path(arg)).items():
            print(f"{arg}  {name}  {digest}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
