"""Write tests/ci_slice.txt, the slice of the slow set CI runs with the default suite: for every test
file with slow tests, its cheapest slow test by measured duration (ties by node id), so that every
slow file's code runs in CI. Deterministic for a given durations log.

    python3 -m pytest -q -m slow --durations=0 > slow.log
    python3 tests/ci_slice.py slow.log

The log's "slowest durations" lines ("12.34s call     tests/x.py::test_y[z]") give each test's
time (setup, call and teardown summed)."""

from __future__ import annotations

import re
import sys
from collections import defaultdict
from pathlib import Path

OUT = Path(__file__).with_name("ci_slice.txt")


def cheapest(log_text: str) -> tuple[list[str], float]:
    took: dict[str, float] = defaultdict(float)
    for m in re.finditer(r"^([0-9.]+)s (?:setup|call|teardown)\s+(\S+)$", log_text, flags=re.M):
        took[m.group(2)] += float(m.group(1))
    by_file: dict[str, list] = defaultdict(list)
    for node, t in took.items():
        by_file[node.split("::")[0]].append((t, node))
    picks = sorted(min(v) for v in by_file.values())
    return sorted(node for _, node in picks), sum(t for t, _ in picks)


def main(argv) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    nodes, total = cheapest(Path(argv[1]).read_text())
    OUT.write_text("# The CI slice of the slow set: the cheapest slow test of each file (tests/ci_slice.py).\n"
                   f"# {len(nodes)} tests, {total:.0f} s measured one by one on 2 CPU cores.\n" + "\n".join(nodes) + "\n")
    print(f"{OUT}: {len(nodes)} tests, {total:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
