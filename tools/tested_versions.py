"""README's table of tested Blender versions, from what the Blender suites of `make test` recorded.

Each suite writes one JSON record into the folder `make test` names (tests/blender/conftest.py,
`AFFINE_SUITE_RECORD`): its label, the Blender and Python it ran on, and its counts. This script
writes them as a table into README.md between the two marker lines, so the table says what ran.

    python tools/tested_versions.py build/suites README.md
"""

from __future__ import annotations

import datetime
import json
import sys
from pathlib import Path

START = "<!-- tested-versions: written by tools/tested_versions.py from `make test`; do not edit -->"
END = "<!-- /tested-versions -->"


def _version_key(record: dict) -> tuple:
    numbers = record["blender"].split()[0].split(".")
    return tuple(int(n) for n in numbers if n.isdigit()), record["label"]


def table(records: list[dict]) -> str:
    rows = ["| Blender | Python | suite | passed | skipped | failed | minutes |",
            "|---|---|---|---|---|---|---|"]
    for record in sorted(records, key=_version_key):
        rows.append(f"| {record['blender']} | {record['python']} | {record['label']} | {record['passed']} | "
                    f"{record['skipped']} | {record['failed']} | {record['seconds'] / 60:.1f} |")
    day = datetime.date.today().isoformat()
    return "\n".join([START, f"The last `make test` ({day}) ran:", "", *rows, END])


def main(folder: str, readme: str) -> int:
    records = [json.loads(p.read_text(encoding="utf-8")) for p in sorted(Path(folder).glob("*.json"))]
    if not records:
        print(f"tested_versions: no suite records in {folder}", file=sys.stderr)
        return 1
    path = Path(readme)
    text = path.read_text(encoding="utf-8")
    if START not in text or END not in text:
        print(f"tested_versions: {readme} has no marker lines for the table", file=sys.stderr)
        return 1
    before, rest = text.split(START, 1)
    after = rest.split(END, 1)[1]
    path.write_text(before + table(records) + after, encoding="utf-8")
    print("\n".join(table(records).splitlines()[1:-1]))
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
