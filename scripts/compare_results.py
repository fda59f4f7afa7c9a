"""Check that a change keeps every result the same: plan the demo objects and compare the files.

    python scripts/compare_results.py make /tmp/before      # on the code before the change
    python scripts/compare_results.py make /tmp/after       # on the code after it
    python scripts/compare_results.py diff /tmp/before /tmp/after

``make`` runs ``pregrasp plan`` on every demo object (the result file of each, the batch report)
and ``pregrasp decompose`` / ``pregrasp pregrasps`` on the default object, in a few settings.
``diff`` compares the files byte for byte after taking out what measures the machine and not the
method: the ``timings`` of each result file (seconds per stage), the report's ``seconds``
column, the generator's version string and the folder the repository sits in (input paths).
Everything else (tree, pool, grasps, contacts, scores, ranks, parameters) must be equal to the
byte. Exit 0 when equal, 1 with the first differences otherwise.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OBJECTS = REPO / "assets" / "objects"

# (name, argv after `pregrasp`), run by `make`; "{out}" is the output folder
RUNS: tuple[tuple[str, list[str]], ...] = (
    ("plan_demo", ["plan", str(OBJECTS), "-o", "{out}/plan_demo", "--report",
                   "{out}/plan_demo/report.csv", "--jobs", "2"]),
    ("plan_mug_5k", ["plan", str(OBJECTS / "mug.obj"), "--points", "5000", "--seed", "3",
                     "--threads", "1", "-o", "{out}/plan_mug_5k.json"]),
    ("decompose_default", ["decompose", str(OBJECTS / "mug_handle.obj"), "-o",
                           "{out}/decompose_default.json"]),
    ("pregrasps_default", ["pregrasps", str(OBJECTS / "mug_handle.obj"), "-o",
                           "{out}/pregrasps_default.json"]),
)  # fmt: skip


def _make(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    # the code of this script's own tree (a git worktree too), whatever is installed
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "OPENBLAS_NUM_THREADS": "1",
        "OMP_NUM_THREADS": "1",
    }
    for name, argv in RUNS:
        args = [a.replace("{out}", str(out.resolve())) for a in argv]
        print(f"compare_results: {name}: pregrasp {' '.join(args[:2])} ...", file=sys.stderr)
        cmd = [sys.executable, "-m", "app.cli", *args]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, cwd=REPO, env=env)


def _normalised(path: Path) -> bytes:
    """The file's bytes without the machine-dependent parts (see the module docstring)."""
    # the input's path names the tree the run was made in (a worktree, a fresh clone)
    raw = re.sub(rb'"[^"]*/assets/objects/', b'"<repo>/assets/objects/', path.read_bytes())
    if path.suffix == ".json":
        doc = json.loads(raw)
        if isinstance(doc, dict):
            doc.pop("timings", None)
            if isinstance(doc.get("generator"), dict):
                doc["generator"].pop("version", None)
        return json.dumps(doc, sort_keys=True, indent=1).encode()
    if path.suffix == ".csv":
        rows = list(csv.DictReader(io.StringIO(raw.decode())))
        for row in rows:
            row.pop("seconds", None)
        return json.dumps(rows, indent=1).encode()
    return raw


def _diff(a: Path, b: Path) -> int:
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file()}
    bad = 0
    for rel in sorted(files_a ^ files_b):
        print(f"only in {'the first' if rel in files_a else 'the second'}: {rel}")
        bad += 1
    for rel in sorted(files_a & files_b):
        x, y = _normalised(a / rel), _normalised(b / rel)
        if x != y:
            bad += 1
            lx, ly = x.splitlines(), y.splitlines()
            first = next((i for i, (u, v) in enumerate(zip(lx, ly, strict=False)) if u != v), 0)
            print(f"differs: {rel} (line {first + 1} of the normalised file)")
            print(f"  - {lx[first][:160] if first < len(lx) else '<end>'!s}")
            print(f"  + {ly[first][:160] if first < len(ly) else '<end>'!s}")
    n = len(files_a & files_b)
    print(f"{n - bad if bad <= n else 0} of {len(files_a | files_b)} files equal")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make", help="write the result files of the demo runs into OUT")
    m.add_argument("out", type=Path)
    d = sub.add_parser("diff", help="compare two folders written by make")
    d.add_argument("a", type=Path)
    d.add_argument("b", type=Path)
    args = p.parse_args(argv)
    if args.cmd == "make":
        _make(args.out)
        return 0
    return _diff(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
