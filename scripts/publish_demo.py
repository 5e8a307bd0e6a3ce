"""Put a demo run's headline table into the README (between its ``<!-- headline -->`` markers; for `--preset olat`,
into docs/guides/reflectance-fields.md between ``<!-- olat-headline -->``) and its results section into
docs/results/demo.md (olat-demo.md), stamped with the run's commit, preset and machine.

    .venv/bin/python scripts/publish_demo.py outputs/demo
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gra_mi.apps.demo_report import headline, results_page, with_block

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="A `gra-mi demo` output folder (its demo.json).")
    args = parser.parse_args(argv)
    source = args.run / "demo.json"
    if not source.is_file():
        print(f"publish_demo: error: {source}: missing (run `gra-mi demo` first)", file=sys.stderr)
        return 2
    record = json.loads(source.read_text())
    static = "refiner" not in record  # `--preset olat`: its own block and page
    block, page = ("olat-headline", "olat-demo.md") if static else ("headline", "demo.md")
    target = ROOT / ("docs/guides/reflectance-fields.md" if static else "README.md")
    target.write_text(with_block(target.read_text(), block, headline(record)))
    (ROOT / "docs" / "results" / page).write_text(results_page(record))
    print(f"updated {target} ({block}) and docs/results/{page} from {source}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
